"""ds3d.util.memory (resident size, the malloc in use) and `ds3d bench memory`."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time

import pytest

from ds3d.cli import main as cli
from ds3d.util.memory import descendants, loaded_allocator, resident_mb, tree_resident_mb
from ds3d_service.allocator import find_jemalloc
from tests.needs import missing


def allocator_of_a_child(env: dict[str, str]) -> str:
    code = "from ds3d.util.memory import loaded_allocator; print(loaded_allocator())"
    out = subprocess.run(
        [sys.executable, "-c", code], env=os.environ | env, capture_output=True, text=True
    )
    return out.stdout.strip()


def test_the_allocator_is_read_from_the_libraries_loaded():
    assert allocator_of_a_child({"LD_PRELOAD": ""}) == "glibc"
    library = find_jemalloc()
    if library is None:
        missing("jemalloc not installed (Debian: apt-get install libjemalloc2)")
    assert allocator_of_a_child({"LD_PRELOAD": library}) == "jemalloc"


@pytest.mark.slow
def test_bench_memory_reports_the_resident_memory_along_the_images(model_dir, tmp_path):
    out = tmp_path / "memory.json"
    args = ["bench", "memory", "--images", "6", "--every", "3", "--malloc-trim"]
    assert cli([*args, "--model-dir", str(model_dir), "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert [row["images"] for row in report["rss_mb"]] == [3, 6]
    assert report["allocator"] == loaded_allocator() and report["malloc_trim"] is True
    # The bench runs in this process: what it reports lies within this process's peak resident
    # size (Linux reports ru_maxrss in KB); its size now is lower once the model is released.
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    assert 100 < report["rss_mb"][-1]["rss_mb"] <= peak_mb * 1.01
    assert report["s_per_image"] > 0
    if report["allocator"] == "glibc":  # its heap: bytes in use and free bytes kept
        assert 0 < report["rss_mb"][-1]["in_use_mb"] < report["rss_mb"][-1]["rss_mb"]


def test_large_buffers_get_their_own_mappings_under_glibc():
    """After map_large_buffers(1 MiB) a freed 8 MB buffer is given back (glibc keeps no free
    memory for it); without it, glibc raises its threshold past such a buffer once one was
    freed, and keeps the next one's memory in its arena. In a child: the setting is for life."""
    code = (
        "import sys; from ds3d.util.memory import glibc_heap_mb, map_large_buffers\n"
        "applied = sys.argv[1] == '1' and map_large_buffers(2**20)\n"
        "for _ in range(2): b = bytearray(8 * 2**20); del b\n"
        "print(applied, glibc_heap_mb()['kept_free_mb'])"
    )
    kept = {}
    for bound in ("0", "1"):
        out = subprocess.run(
            [sys.executable, "-c", code, bound],
            env=os.environ | {"LD_PRELOAD": ""},
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()
        assert out[0] == str(bound == "1")
        kept[bound] = float(out[1])
    assert kept["1"] < 8 <= kept["0"]


def test_a_process_tree_is_found_and_its_memory_summed():
    """A child and its own child are this process's descendants, and the tree's resident
    memory is at least this process's and the children's, each of them a Python."""
    sleeper = "import time; time.sleep(30)"
    grandchild = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {sleeper!r}])"
    child = subprocess.Popen([sys.executable, "-c", grandchild])
    try:
        deadline = time.monotonic() + 20
        while len(descendants(os.getpid())) < 2:
            assert time.monotonic() < deadline, "the grandchild never started"
            time.sleep(0.05)
        tree = descendants(os.getpid())
        assert child.pid in tree
        assert tree_resident_mb() >= resident_mb() + sum(resident_mb(p) for p in tree) - 1
        assert resident_mb(child.pid) > 1
    finally:
        for pid in descendants(child.pid):
            os.kill(pid, 9)
        child.kill()
        child.wait()
    assert resident_mb(child.pid) == 0.0  # gone
