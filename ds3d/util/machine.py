"""What this process may use of the machine: its CPU cores and its memory, as a container's
limits (cgroup v2) or the CPU affinity narrow them, so that defaults sized from them fit a
laptop, a CPU server and a pod alike."""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP = Path("/sys/fs/cgroup")


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
