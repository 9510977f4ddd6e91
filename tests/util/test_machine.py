"""What a process may use of the machine (ds3d.util.machine), and the defaults sized from it: the
service's (ds3d_service.settings) and the commands' (ds3d.cli.parser) workers and threads."""

import math

import pytest

from ds3d.util import machine
from ds3d.util.machine import usable_cpus, usable_memory_mb


def test_a_cgroup_cpu_quota_narrows_the_cores(tmp_path):
    cores = usable_cpus(tmp_path)  # no cpu.max: the affinity alone
    assert cores >= 1
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert usable_cpus(tmp_path) == cores
    (tmp_path / "cpu.max").write_text("150000 100000\n")  # 1.5 cores: 2 to run on
    assert usable_cpus(tmp_path) == min(cores, 2)
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert usable_cpus(tmp_path) == 1


def test_a_cgroup_memory_limit_narrows_the_available_memory(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal: 24000000 kB\nMemAvailable: 20480000 kB\n")
    assert usable_memory_mb(tmp_path, meminfo) == 20000
    (tmp_path / "memory.max").write_text("max\n")
    (tmp_path / "memory.current").write_text(str(2**30))
    assert usable_memory_mb(tmp_path, meminfo) == 20000
    (tmp_path / "memory.max").write_text(str(4 * 2**30))
    assert usable_memory_mb(tmp_path, meminfo) == 3 * 1024
    assert usable_memory_mb(tmp_path / "none", tmp_path / "none") == math.inf


@pytest.mark.parametrize(
    ("cpus", "memory_mb", "workers", "threads"),
    [
        (2, 20000, 2, 1),  # this machine: two processes of one thread
        (1, 20000, 1, 1),  # a pod of one CPU
        (8, 3500, 2, 2),  # few GB: as many workers as fit, the cores shared among them
        (16, 100000, 16, 1),
        (4, 1500, 1, 2),  # not even one worker beside the service: one process
    ],
)
def test_the_service_sizes_its_workers_and_threads_from_the_machine(
    monkeypatch, cpus, memory_mb, workers, threads
):
    from ds3d_service import settings

    monkeypatch.setattr(machine, "usable_cpus", lambda: cpus)
    monkeypatch.setattr(machine, "usable_memory_mb", lambda: memory_mb)
    monkeypatch.setattr(machine, "shared_memory_writable", lambda: True)
    for name in ("DS3D_WORKERS", "DS3D_TORCH_THREADS", "DS3D_DEVICE"):
        monkeypatch.delenv(name, raising=False)
    chosen = settings.Settings()
    assert (chosen.workers, chosen.torch_threads) == (workers, threads)
    assert settings.Settings(device="cuda").workers == 1
    assert settings.Settings(workers=1).torch_threads == min(2, cpus)
    from ds3d.cli.parser import build_parser, resolve_workers

    args = build_parser().parse_args(["bench", "pipeline"])
    resolve_workers(args)
    assert (args.workers, args.threads) == (workers, threads)
    args = build_parser().parse_args(["bench", "pipeline", "--workers", "1"])
    resolve_workers(args)
    assert (args.workers, args.threads) == (1, min(2, cpus))


def test_without_shared_memory_one_process_serves(monkeypatch, tmp_path):
    assert machine.shared_memory_writable(tmp_path)
    assert not machine.shared_memory_writable(tmp_path / "none")
    monkeypatch.setattr(machine, "usable_cpus", lambda: 8)
    monkeypatch.setattr(machine, "usable_memory_mb", lambda: 100000)
    monkeypatch.setattr(machine, "shared_memory_writable", lambda: False)
    assert machine.default_workers() == 1 and machine.default_threads(1) == 2


def test_the_module_reads_the_real_machine():
    assert machine.usable_cpus() >= 1 and machine.usable_memory_mb() > 0
