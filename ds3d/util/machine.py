"""What this process may use of the machine: its CPU cores and its memory, as a container's
limits (cgroup v2) or the CPU affinity narrow them, so that defaults sized from them fit a
laptop, a CPU server and a pod alike."""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP = Path("/sys/fs/cgroup")
# What sizes the default worker processes of a pipeline on a CPU (ds3d.runners.workers): the
# resident memory of one (its own Pipeline: 0.80 GB after LSP images, docs/service-results.md)
# and of the process that starts them (the service's, with its lifter for /v1/lift: 0.72 GB),
# each with a margin.
WORKER_MB = 1024
MAIN_MB = 1024


def usable_cpus(cgroup: Path = CGROUP) -> int:
    """The cores this process may run on: its CPU affinity, within its cgroup's CPU quota
    (cpu.max, e.g. `200000 100000` = 2 cores) where one is set; at least 1."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    quota = _read(cgroup / "cpu.max")
    if quota is not None and not quota.startswith("max"):
        limit, period = (int(v) for v in quota.split()[:2])
        cores = min(cores or 1, math.ceil(limit / period))
    return max(1, cores or 1)


def usable_memory_mb(cgroup: Path = CGROUP, meminfo: Path = Path("/proc/meminfo")) -> float:
    """The memory this process may still take, MB: the system's available memory
    (MemAvailable), within what its cgroup's limit (memory.max) leaves above its use
    (memory.current) where one is set; infinite where neither is known."""
    available = math.inf
    text = _read(meminfo)
    for line in (text or "").splitlines():
        if line.startswith("MemAvailable:"):
            available = int(line.split()[1]) / 1024
    limit, used = _read(cgroup / "memory.max"), _read(cgroup / "memory.current")
    if limit is not None and limit.strip() != "max" and used is not None:
        available = min(available, (int(limit) - int(used)) / 2**20)
    return available


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None


def default_workers(device: str = "cpu") -> int:
    """Worker processes that suit this machine for a pipeline on `device`: one per usable core,
    as many as the available memory holds (WORKER_MB each beside MAIN_MB); 1 on a GPU, which
    one process keeps busy, and where no shared memory can be written. On a CPU processes give
    more images/s than as many threads: the 2D stage's Python holds the interpreter's lock for
    part of its time."""
    if device != "cpu" or not shared_memory_writable():
        return 1
    fits = int((usable_memory_mb() - MAIN_MB) // WORKER_MB)
    return max(1, min(usable_cpus(), fits))


def shared_memory_writable(folder: Path = Path("/dev/shm")) -> bool:
    """Whether this process may write POSIX shared memory, through which worker processes share
    their barrier and tensors (some sandboxes mount none, or none for this user)."""
    return os.access(folder, os.W_OK | os.X_OK)


def default_threads(workers: int) -> int:
    """torch threads per worker: the usable cores shared among `workers`, at most 2 each (a
    third pays little), at least 1."""
    return max(1, min(2, usable_cpus() // workers))
