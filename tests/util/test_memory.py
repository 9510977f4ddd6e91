"""ds3d.util.memory (resident size, the malloc in use) and `ds3d bench memory`."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from ds3d.cli import main as cli
from ds3d.util.memory import loaded_allocator, resident_mb
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
    assert 100 < report["rss_mb"][-1]["rss_mb"] <= resident_mb() * 1.5
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
