"""`ds3d predict` and the Python predictions (ds3d.cli.pipeline, ds3d.runners.predict)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ds3d.cli import main as cli
from ds3d.data.bvh import forward_kinematics, read_bvh
from ds3d.data.lsp import load_lsp
from ds3d.io.images import read_image
from ds3d.kinematics import JOINT_NODES, NODES
from ds3d.skeleton import NUM_JOINTS
from ds3d.util.paths import MODELS_DIR


def _clip(path, image, count=4, fps=12.0):
    """An MP4 of `count` frames of `image` (RGB), shifted a little each frame."""
    height, width = image.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
    for k in range(count):
        writer.write(np.ascontiguousarray(np.roll(image[..., ::-1], 2 * k, axis=1)))
    writer.release()


@pytest.mark.slow
def test_predict_streams_a_folder_and_a_video_and_writes_every_output(data_dir, tmp_path):
    paths = load_lsp(split="test").image_paths[:3]
    folder = tmp_path / "photos"
    (folder / "more").mkdir(parents=True)
    (folder / "a.jpg").write_bytes(paths[0].read_bytes())
    (folder / "more" / "b").write_bytes(paths[1].read_bytes())  # found by content
    (folder / "broken.jpg").write_bytes(paths[2].read_bytes()[:300])
    _clip(tmp_path / "clip.mp4", read_image(paths[2]))
    out = tmp_path / "out"
    args = ["--quiet", "predict", str(folder), str(tmp_path / "clip.mp4"), str(tmp_path / "no.jpg")]
    # the bundled models: the small test model's poses jump between frames, so would its tracks
    args += ["--stride", "2", "--batch-size", "3", "--out", str(out)]
    args += ["--model-dir", str(MODELS_DIR)]
    assert cli([*args, "--json", "--coco", "--overlay", "--bvh"]) == 0

    lines = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()]
    errors = {Path(line["source"]).name: line["error"] for line in lines if "error" in line}
    assert set(errors) == {"broken.jpg", "no.jpg"} and "truncated" in errors["broken.jpg"]
    done = [line for line in lines if "error" not in line]
    assert [(Path(d["source"]).name, d["frame"]) for d in done] == [
        ("a.jpg", None), ("b", None), ("clip.mp4", 0), ("clip.mp4", 2)
    ]  # fmt: skip
    person = done[0]["people"][0]
    # a video's people are tracked: the clip's one person keeps its id
    assert person["track_id"] is None and [d["people"][0]["track_id"] for d in done[2:]] == [0, 0]
    assert np.asarray(person["joints_3d"]).shape == (NUM_JOINTS, 3)
    assert len(list((out / "json").iterdir())) == 4
    assert len(list((out / "overlay").glob("*.jpg"))) == 2  # the stills; the video as MP4

    coco = json.loads((out / "coco_keypoints.json").read_text())
    assert len(coco["images"]) == 4 and len(coco["annotations"]) == 4
    keypoints = np.asarray(coco["annotations"][0]["keypoints"]).reshape(17, 3)
    assert (keypoints[:5, 2] == 0).all()  # no face in LSP
    # visible (2) where the joint is likely right, else labelled (1)
    sure = np.asarray(coco["annotations"][0]["keypoint_scores"])[5:] >= 0.5
    assert (keypoints[5:, 2] == np.where(sure, 2, 1)).all()
    # COCO's left shoulder is LSP's left shoulder
    np.testing.assert_allclose(keypoints[5, :2], person["joints_2d"][9], atol=0.01)

    sequence = np.load(out / "clip_3d.npz")
    assert sequence["frame"].tolist() == [0, 2] and sequence["joints_3d"].shape == (2, 14, 3)
    assert float(sequence["fps"]) == pytest.approx(12.0)
    rows = (out / "clip_3d.csv").read_text().splitlines()
    assert rows[0] == "frame,time_s,joint,x_mm,y_mm,z_mm" and len(rows) == 1 + 2 * NUM_JOINTS
    video = cv2.VideoCapture(str(out / "clip_overlay.mp4"))
    ok, frame = video.read()
    assert ok and int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 2
    _, source = cv2.VideoCapture(str(tmp_path / "clip.mp4")).read()
    assert frame.shape[0] == source.shape[0] and frame.shape[1] > source.shape[1]  # 3D beside

    # the joint angles as BVH: a one-frame file per still image's person, a file per video; the
    # project's reader places the joints where the answers put them (camera axes to y up)
    stills = sorted((out / "bvh").glob("*.bvh"))
    assert [p.name for p in stills] == ["000001_a_0.bvh", "000002_b_0.bvh"]
    placed = np.asarray(person["joints_3d_camera"]) * [1, -1, -1]
    motion = read_bvh(stills[0])
    joints = forward_kinematics(motion)[0, [motion.index(NODES[n].name) for n in JOINT_NODES]]
    np.testing.assert_allclose(joints, placed, atol=0.01)
    clip = read_bvh(out / "clip_0.bvh")  # the clip's one tracked person
    assert clip.num_frames == 2 and clip.frame_time == pytest.approx(2 / 12.0, abs=1e-6)


@pytest.mark.slow
def test_predict_from_python_yields_results_that_plot(model_dir, data_dir):
    from ds3d import predict
    from ds3d.pipeline import Pipeline

    pipeline = Pipeline.load(model_dir)
    paths = load_lsp(split="test").image_paths[:2]
    array = read_image(paths[1])
    skipped = []
    results = list(
        predict(
            [str(paths[0]), "missing.png", array], pipeline, batch_size=2, on_skip=skipped.append
        )
    )
    assert [r.source for r in results] == [str(paths[0]), "array:2"]
    assert [f.source for f in skipped] == ["missing.png"]
    picture = results[1].plot()
    assert picture.shape[0] == array.shape[0] and picture.shape[1] > array.shape[1]
    assert results[1].plot(with_3d=False).shape == array.shape


@pytest.mark.slow
def test_predict_refuses_a_box_an_image_cannot_hold_and_goes_on(model_dir, data_dir, tmp_path):
    image = load_lsp(split="test").image_paths[0]
    out = tmp_path / "out"
    args = ["--quiet", "predict", str(image), "--bbox", "5000,5,90,150", "--out", str(out)]
    assert cli([*args, "--model-dir", str(model_dir)]) == 0
    (line,) = (out / "predictions.jsonl").read_text().splitlines()
    assert "outside" in json.loads(line)["error"]


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


@pytest.mark.slow
def test_predict_on_worker_processes_writes_what_one_process_does(data_dir, tmp_path):
    """--workers 2: the batch split between two processes of the bundled models; the same 2D
    joints per image as one process (the 3D within the fit's rounding)."""
    images = tmp_path / "images"
    images.mkdir()
    for path in load_lsp(split="test").image_paths[:3]:
        (images / path.name).write_bytes(path.read_bytes())
    answers = {}
    for workers in ("1", "2"):
        out = tmp_path / f"out{workers}"
        args = ["--quiet", "predict", str(images), "--out", str(out), "--workers", workers]
        assert cli([*args, "--threads", "1"]) == 0
        lines = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()]
        answers[workers] = {a["source"]: a["people"][0] for a in lines}
    assert answers["1"].keys() == answers["2"].keys() and len(answers["1"]) == 3
    for source, alone in answers["1"].items():
        pooled = answers["2"][source]
        np.testing.assert_allclose(pooled["joints_2d"], alone["joints_2d"], atol=1e-3)
        np.testing.assert_allclose(pooled["joints_3d"], alone["joints_3d"], atol=1.0)


@pytest.mark.slow
def test_eval_people_fits_the_person_score_on_more_canvases_when_asked(data_dir, tmp_path):
    """`--calibrate-also` adds another split's canvases, drawn alike, to the person score's fit
    (calibration_pooled) and leaves the run's own figures and fit as they are; `--plot` draws
    the score's reliability diagram."""
    common = ["--quiet", "eval", "people", "--split", "train", "--start", "700", "--count", "2"]
    common = [*common, "--threads", "1"]
    alone, pooled, plot = tmp_path / "alone.json", tmp_path / "pooled.json", tmp_path / "r.png"
    assert cli([*common, "--plot", str(plot), "--out", str(alone)]) == 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert cli([*common, "--calibrate-also", "lspet:9000", "--out", str(pooled)]) == 0
    alone_report, report = json.loads(alone.read_text()), json.loads(pooled.read_text())
    assert report["calibration"] == alone_report["calibration"]
    assert report["large"] == alone_report["large"]
    assert report["calibration_pooled"]["with"] == ["lspet:9000"]
    assert report["calibration_pooled"]["candidates"] > report["calibration"]["candidates"]
    assert "calibration_pooled" not in alone_report
