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


def test_gallery_of_photos_renders_every_photo_of_a_folder(data_dir, tmp_path):
    """Every photo (by its suffix) of the folder gets a render of the people found; other files
    are passed over."""
    photos = tmp_path / "photos"
    photos.mkdir()
    image = load_lsp(split="test").image_paths[0]
    (photos / "person.jpg").write_bytes(image.read_bytes())
    (photos / "notes.txt").write_text("not a photo")
    assert cli(["gallery", "--photos", str(photos), "--out", str(tmp_path / "out")]) == 0
    (render,) = (tmp_path / "out" / "photos").iterdir()
    assert render.name == "person.png" and render.read_bytes()[:4] == b"\x89PNG"


def test_eval_lsp_pipeline_scores_the_searched_pipeline_beside_the_crops(data_dir, tmp_path):
    out = tmp_path / "report.json"
    args = ["eval", "lsp-pipeline", "--limit", "4", "--variants", "full", "--searched"]
    assert cli([*args, "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert {"initial", "full/iteration1", "searched"} <= set(report["results"])
    assert 0.0 <= report["results"]["searched"]["pck@0.2"] <= 1.0
