"""tools.bvh_strip, the README's picture of the BVH path, still draws."""

from __future__ import annotations

from tools.bvh_strip import main


def test_the_strip_is_drawn(data_dir, tmp_path):
    out = tmp_path / "strip.png"
    assert main([str(out), "--start", "0", "--every", "5", "--frames", "2"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
