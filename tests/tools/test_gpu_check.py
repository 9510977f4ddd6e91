"""tools.gpu_check's data pack: what a bare GPU machine evaluates on is the protocol's data."""

from __future__ import annotations

import numpy as np

from ds3d.data.lsp import load_lsp
from ds3d.evaluation.h36m import protocol_cases
from tools.gpu_check import _pins, pack


def test_the_packed_subset_holds_the_protocols_frames_and_images(data_dir, tmp_path, monkeypatch):
    pack(tmp_path, images=3, wheels=False)
    full = protocol_cases(stride=64)
    monkeypatch.setenv("DS3D_DATA", str(tmp_path / "data"))
    packed = protocol_cases(stride=1)
    np.testing.assert_array_equal(packed.joints_2d, full.joints_2d)
    np.testing.assert_array_equal(packed.joints_3d, full.joints_3d)
    lsp = load_lsp(split="test")
    assert [p.name for p in lsp.image_paths if p.is_file()] == [
        "im1001.jpg",
        "im1002.jpg",
        "im1003.jpg",
    ]


def test_the_wheels_are_pinned_by_the_service_lock():
    pins = _pins()
    assert pins["faiss-cpu"].startswith("faiss-cpu==") and pins["fastapi"].startswith("fastapi==")
