"""Where a measured figure comes from: the commit, the machine and the date of a run, recorded in
every JSON report the project writes (ds3d.cli.parser.write_report, the tools' reports), so that
a figure in the docs can be traced to the tree and the machine it was measured on."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path

from ds3d.util.machine import usable_cpus, usable_memory_mb

ROOT = Path(__file__).resolve().parents[2]  # a checkout's root (an install has no .git there)


def provenance(argv: list[str] | None = None) -> dict:
    """{"commit", "dirty", "date", "machine", "command"}: the checkout's commit (None outside
    one) and whether its tracked files differ from it, the UTC time, the machine (machine()),
    and the command line (argv, default sys.argv)."""
    argv = sys.argv if argv is None else argv
    return {
        "commit": _git("rev-parse", "HEAD"),
        "dirty": bool(_git("status", "--porcelain", "--untracked-files=no")),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": machine(),
        "command": " ".join([Path(argv[0]).name, *argv[1:]]) if argv else "",
    }


def machine() -> dict:
    """The CPU model, its cores (all, and those this process may use), the memory, and the GPU
    torch sees where it is already loaded (None otherwise)."""
    torch = sys.modules.get("torch")
    gpu = torch.cuda.get_device_name() if torch is not None and torch.cuda.is_available() else None
    return {
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "usable_cores": usable_cpus(),
        "memory_gb": round(_total_memory_mb() / 1024, 1),
        "available_memory_gb": round(usable_memory_mb() / 1024, 1),
        "gpu": gpu,
    }


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _total_memory_mb() -> float:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _git(*args: str) -> str | None:
    """A git command's output in the checkout, or None where there is none."""
    try:
        run = subprocess.run(
            ["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return run.stdout.strip() if run.returncode == 0 else None
