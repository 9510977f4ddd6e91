"""The process's memory: its resident size, the malloc it runs on, and glibc's trim.

What grows in a long-running process is read here (`ds3d bench memory`, the service's /metrics
and its allocator choice, ds3d_service/allocator.py).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path


def resident_mb(pid: int | str = "self", proc: Path = Path("/proc")) -> float:
    """A process's resident memory in MB (this one's by default; Linux; 0.0 elsewhere or where
    it has gone)."""
    try:
        pages = int((proc / str(pid) / "statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def descendants(pid: int, proc: Path = Path("/proc")) -> list[int]:
    """The processes started by process `pid`, theirs, and so on (Linux: from each process's
    parent in /proc/PID/stat; [] elsewhere)."""
    children: dict[int, list[int]] = {}
    for stat in proc.glob("[0-9]*/stat"):
        try:  # "pid (name) state ppid ...": the name may hold spaces and parentheses
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # gone meanwhile
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        found += kids
        todo += kids
    return found


def tree_resident_mb(pid: int | None = None, proc: Path = Path("/proc")) -> float:
    """The resident memory in MB of a process (this one by default) and of all its descendants
    (a server and its worker processes). Pages the processes share (libraries, shared memory)
    are counted once per process: an upper bound of what they take together."""
    pid = os.getpid() if pid is None else pid
    return sum(resident_mb(p, proc) for p in [pid, *descendants(pid, proc)])


def loaded_allocator() -> str:
    """ "jemalloc", "tcmalloc" or "glibc": the malloc this process runs on (Linux; from the
    libraries mapped into it)."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return "glibc"
    for name in ("jemalloc", "tcmalloc"):
        if f"lib{name}" in maps:
            return name
    return "glibc"


def malloc_trim() -> None:
    """Give glibc malloc's free pages back to the system (malloc_trim(0)); a no-op under
    another allocator."""
    if loaded_allocator() == "glibc":
        ctypes.CDLL("libc.so.6").malloc_trim(0)


# mallopt's parameter for the size from which an allocation gets its own mapping (malloc.h).
_M_MMAP_THRESHOLD = -3


def map_large_buffers(threshold_bytes: int) -> bool:
    """Under glibc's malloc, give every allocation of at least `threshold_bytes` its own mapping,
    returned to the system when it is freed. By default glibc raises that threshold to the
    largest buffer freed so far (up to 32 MB), after which buffers of every size come from its
    arenas, which keep the free memory around them. Returns whether it applied (False under
    another allocator)."""
    if loaded_allocator() != "glibc":
        return False
    return bool(ctypes.CDLL("libc.so.6").mallopt(_M_MMAP_THRESHOLD, threshold_bytes))


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost"
        ).split()
    ]


def glibc_heap_mb() -> dict[str, float] | None:
    """glibc malloc's bytes in use and free bytes it keeps (all arenas, mallinfo2), in MB; None
    under another allocator. What fragmentation looks like: in use flat, kept free rising."""
    if loaded_allocator() != "glibc":
        return None
    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = _MallInfo2
    info = libc.mallinfo2()
    return {
        "in_use_mb": round((info.uordblks + info.hblkhd) / 2**20, 1),
        "kept_free_mb": round(info.fordblks / 2**20, 1),
    }
