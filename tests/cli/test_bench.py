"""`ds3d bench pipeline` (ds3d.cli.bench): the figures RESULTS quotes come from its report."""

from __future__ import annotations

import json

import pytest

from ds3d.cli import main as cli


@pytest.mark.slow
def test_bench_pipeline_reports_searched_and_boxed_images_on_its_device(
    model_dir, data_dir, tmp_path
):
    reports = {}
    for name, extra in (("searched", []), ("boxes", ["--boxes"])):
        out = tmp_path / f"{name}.json"
        args = ["--quiet", "bench", "pipeline", "--batch-sizes", "2", "--repeats", "1"]
        args += ["--device", "cpu", "--model-dir", str(model_dir), *extra, "--out", str(out)]
        assert cli(args) == 0
        reports[name] = json.loads(out.read_text())
    for name, report in reports.items():
        assert report["device"] == "cpu" and report["boxes"] == (name == "boxes")
        (row,) = report["rows"]
        assert row["batch"] == 2 and row["images_per_s"] > 0
