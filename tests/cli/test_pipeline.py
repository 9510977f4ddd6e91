"""`ds3d predict` (ds3d.cli.pipeline)."""

from __future__ import annotations

import json

import numpy as np

from ds3d.cli import main as cli
from ds3d.data.lsp import load_lsp
from ds3d.skeleton import NUM_JOINTS


def test_predict_command_writes_json_and_a_picture(model_dir, data_dir, tmp_path):
    image = load_lsp(split="test").image_paths[0]
    out, png = tmp_path / "result.json", tmp_path / "pose.png"
    args = ["predict", str(image), "--bbox", "5,5,90,150", "--iterations", "1", "--out", str(out)]
    assert cli([*args, "--render", str(png), "--model-dir", str(model_dir)]) == 0
    report = json.loads(out.read_text())
    (item,) = report["items"]
    assert np.asarray(item["joints_3d"]).shape == (NUM_JOINTS, 3) and item["iterations"] == 1
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
