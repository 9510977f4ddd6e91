"""`ds3d batch` (ds3d.cli.ray_data, ds3d.runners.ray_data): listing, resuming, a run on a local
Ray."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ds3d.cli import main as cli
from ds3d.runners.ray_data import (
    ERRORS,
    PREDICTIONS,
    BatchOptions,
    done_sources,
    estimate_paths,
    list_images,
    parse_actors,
)
from ds3d.skeleton import NUM_JOINTS
from tests.needs import import_or_missing

JPEG = b"\xff\xd8\xff\xe0" + bytes(12)  # a JPEG's first bytes: found as an image by content


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_list_images_reads_folders_globs_and_list_files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "photos" / "sub").mkdir(parents=True)
    for name in ("photos/a.jpg", "photos/sub/b", "c.jpg"):
        (tmp_path / name).write_bytes(JPEG)
    (tmp_path / "photos" / "notes.txt").write_text("not an image")  # passed over, as predict
    (tmp_path / "list.txt").write_text("# my images\nc.jpg\n\nphotos/a.jpg\nmissing.jpg\n")
    paths, errors = list_images(["photos", "*.jpg", "list.txt", "nothing/*.png"])
    names = [os.path.relpath(p, tmp_path) for p in paths]
    assert names == ["photos/a.jpg", "photos/sub/b", "c.jpg", "missing.jpg"]  # no repeats
    assert all(os.path.isabs(p) for p in paths)
    assert errors == [{"source": "nothing/*.png", "error": "the pattern matches no file"}]


def test_done_sources_cuts_a_partial_last_line_and_counts_errors_unless_retried(tmp_path):
    (tmp_path / PREDICTIONS).write_text('{"source": "/a.jpg", "people": []}\n{"source": "/b.j')
    (tmp_path / ERRORS).write_text('{"source": "/c.jpg", "error": "truncated"}\n')
    assert done_sources(tmp_path) == {"/a.jpg", "/c.jpg"}
    assert done_sources(tmp_path, retry_errors=True) == {"/a.jpg"}
    assert (tmp_path / PREDICTIONS).read_text().endswith("[]}\n")  # appending is safe again


class _NobodyPipeline:
    """Pipeline.run's stand-in: finds nobody, and fails on a batch holding a 3-px-wide image."""

    def run(self, inputs, iterations=None):
        from ds3d.result import PipelineResult

        if any(item.image.shape[1] == 3 for item in inputs):
            raise RuntimeError("too narrow")
        return PipelineResult.empty(1, {})


def test_estimate_paths_records_every_bad_file_and_keeps_the_rest(tmp_path):
    import cv2

    files = {"ok.png": (8, 8), "narrow.png": (8, 3), "big.png": (40, 40)}
    for name, shape in files.items():
        cv2.imwrite(str(tmp_path / name), np.zeros((*shape, 3), np.uint8))
    (tmp_path / "text.jpg").write_text("not an image")
    paths = [str(tmp_path / n) for n in ("ok.png", "narrow.png", "big.png", "text.jpg", "no.png")]
    out = estimate_paths(_NobodyPipeline(), paths, BatchOptions(max_pixels=1000))
    rows = {Path(s).name: (r, e) for s, r, e in zip(*out.values(), strict=True)}
    assert json.loads(rows["ok.png"][0]) == {
        "source": paths[0], "frame": None, "width": 8, "height": 8, "people": []
    }  # fmt: skip
    assert rows["narrow.png"][1] == "estimate failed: RuntimeError: too narrow"
    assert "more than the limit of 1000" in rows["big.png"][1]
    assert "not an image" in rows["text.jpg"][1]
    assert rows["no.png"][1].startswith("cannot read:")


def test_parse_actors():
    assert parse_actors("3") == 3 and parse_actors("1,4") == (1, 4)
    for bad in ("0", "4,1", "x", "1,2,3"):
        with pytest.raises(ValueError):
            parse_actors(bad)


@pytest.mark.slow
def test_the_cli_imports_no_ray_and_batch_says_how_to_install_it(tmp_path, monkeypatch):
    code = "import sys; from ds3d.cli.parser import build_parser; build_parser(); "
    code += "import ds3d.runners.ray_data; assert 'ray' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed: `import ray` fails
    with pytest.raises(SystemExit, match=r"pip install -e '\.\[ray\]'"):
        cli(["batch", str(tmp_path), "--out", str(tmp_path / "out")])


@pytest.fixture
def local_ray():
    """A single-node Ray of 2 CPUs for the test, shut down after."""
    ray = import_or_missing("ray", "Ray is an optional extra: pip install -e '.[ray]'")
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        object_store_memory=200 * 1024 * 1024,
        logging_level="ERROR",
    )
    yield ray
    ray.shutdown()


@pytest.mark.slow
def test_batch_estimates_a_folder_records_a_corrupt_file_and_resumes(
    local_ray, model_dir, data_dir, tmp_path, capsys
):
    from ds3d.data.lsp import load_lsp

    folder = tmp_path / "photos"
    folder.mkdir()
    paths = load_lsp(split="test").image_paths[:5]
    for path in paths[:4]:
        (folder / path.name).write_bytes(path.read_bytes())
    (folder / "broken.jpg").write_bytes(paths[4].read_bytes()[:600])  # half a JPEG, or less
    out = tmp_path / "out"
    args = ["--quiet", "batch", str(folder), "--out", str(out), "--model-dir", str(model_dir)]
    args += ["--actors", "2", "--batch-size", "2"]
    assert cli(args) == 0

    records = _lines(out / PREDICTIONS)
    assert sorted(Path(r["source"]).name for r in records) == sorted(p.name for p in paths[:4])
    for record in records:  # the record of `ds3d predict`
        assert {"source", "frame", "width", "height", "people"} <= set(record)
        (person,) = record["people"]  # people="best": one each
        assert np.asarray(person["joints_3d"]).shape == (NUM_JOINTS, 3)
        assert np.asarray(person["joints_2d"]).shape == (NUM_JOINTS, 2)
    (error,) = _lines(out / ERRORS)
    assert Path(error["source"]).name == "broken.jpg" and "truncated" in error["error"]
    assert "4 estimated, 1 errors" in capsys.readouterr().err

    assert cli(args) == 0  # the re-run has nothing left to do
    assert "5 images: 5 already done, 0 to do" in capsys.readouterr().err
    assert len(_lines(out / PREDICTIONS)) == 4 and len(_lines(out / ERRORS)) == 1
