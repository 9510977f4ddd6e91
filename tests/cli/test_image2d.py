"""`ds3d eval lsp` and the `--set` machinery (ds3d.cli)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from ds3d.cli import main as cli
from ds3d.cli.image2d import evaluate_validation
from ds3d.cli.parser import field_overrides
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.params import EstimatorParams
from ds3d.training.config import TrainConfig
from ds3d.util.paths import MODELS_DIR, project_relative


@pytest.mark.usefixtures("data_dir")
def test_eval_lsp_on_held_out_train_images_with_an_override(small_model, tmp_path):
    out = tmp_path / "val.json"
    argv = ["lsp", "--model", str(small_model), "--split", "train", "--start", "990"]
    argv += ["--set", "n_scales=2", "--out", str(out)]
    assert cli(["eval", *argv]) == 0
    report = json.loads(out.read_text())
    assert report["dataset"] == "LSP train im0991-im1000" and report["n_images"] == 10
    assert report["overrides"] == ["n_scales=2"]
    assert report["model"] == str(small_model)  # outside the project: as given
    assert project_relative(MODELS_DIR / "image2d") == "models/image2d"  # same on any checkout
    for name in ("psm", "unary_argmax"):
        assert 0 <= report[name]["pck@0.2"] <= 1 and len(report[name]["pck@0.2_per_joint"]) == 14
    overrides = ["observer_labels=false", "stride=4", "unary_weight=1.5", "coarse_trees=none"]
    assert field_overrides(EstimatorParams, overrides) == {
        "observer_labels": False,
        "stride": 4,
        "unary_weight": 1.5,
        "coarse_trees": None,
    }
    assert field_overrides(EstimatorParams, ["coarse_trees=6"]) == {"coarse_trees": 6}
    with pytest.raises(SystemExit, match=re.escape("is not a int | None")):
        field_overrides(EstimatorParams, ["coarse_trees=six"])
    with pytest.raises(SystemExit, match="not a InferenceParams field"):
        cli(["eval", "lsp", "--model", str(small_model), "--set", "n_scale=2"])
    with pytest.raises(SystemExit, match="is not a bool"):
        cli(["eval", "lsp", "--model", str(small_model), "--set", "flip_test=maybe"])
    # What training fixed is not for inference to change: the models were grown for it.
    with pytest.raises(SystemExit, match="not a InferenceParams field"):
        cli(["eval", "lsp", "--model", str(small_model), "--set", "stride=4"])
    with pytest.raises(ValueError, match="not an inference parameter: stride"):
        EstimatorParams().with_inference(stride=4)


@pytest.mark.usefixtures("data_dir")
def test_eval_lsp_on_lspet_scores_the_placed_joints_of_images_with_a_torso(small_model, tmp_path):
    out = tmp_path / "lspet.json"
    argv = ["lsp", "--model", str(small_model), "--split", "lspet", "--start", "9000"]
    assert cli(["eval", *argv, "--limit", "12", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["dataset"] == "LSPet im09001-im09012"
    # LSPet leaves unplaced the joints it does not see, torso joints too: of these 12 images,
    # 10 have both ends of a torso diagonal placed (ds3d.evaluation.lsp.with_torso).
    assert report["n_images"] == 10 and report["n_images_without_torso"] == 2
    assert 0 <= report["psm"]["pck@0.2"] <= 1


@pytest.mark.usefixtures("data_dir")
def test_validation_scores_both_held_out_sets(small_model):
    # what train-2d and train-jointnet record as the manifest's metrics.validation
    result = evaluate_validation(small_model, TrainConfig(n_val=4, lspet_val=12))
    assert result["n_images"] == 4  # LSP train im0997-im1000
    lspet = result["lspet"]  # LSPet im09989-im10000, those with a torso diagonal scored
    assert lspet["n_images"] + lspet.get("n_images_without_torso", 0) == 12
    without = evaluate_validation(small_model, TrainConfig(n_val=4, lspet_val=0))
    assert "lspet" not in without and without["psm"] == result["psm"]


def test_set_takes_a_tuple_as_comma_separated_values():
    overrides = ["jointnet_widths=32,64,96", "jointnet_blocks=1,1,2"]
    assert field_overrides(TrainConfig, overrides) == {
        "jointnet_widths": (32, 64, 96),
        "jointnet_blocks": (1, 1, 2),
    }
    with pytest.raises(SystemExit, match="is not a tuple"):
        field_overrides(TrainConfig, ["jointnet_widths=32,64"])
    with pytest.raises(SystemExit, match="is not a tuple"):
        field_overrides(TrainConfig, ["jointnet_widths=32,64,wide"])


@pytest.mark.slow
@pytest.mark.usefixtures("data_dir")
def test_train_2d_without_network_then_train_jointnet_with_overrides(tmp_path):
    model = tmp_path / "image2d"
    argv = ["train-2d", "--small", "--no-jointnet", "--no-eval", "--out", str(model)]
    assert cli(argv) == 0
    assert json.loads((model / "manifest.json").read_text())["jointnet"] is None
    argv = ["train-jointnet", "--model", str(model), "--no-eval", "--set", "jointnet_epochs=1"]
    assert cli([*argv, "--set", "jointnet_widths=8,16,24", "--set", "jointnet_blocks=1,1,1"]) == 0
    manifest = json.loads((model / "manifest.json").read_text())
    assert manifest["jointnet_shape"] == {"widths": [8, 16, 24], "blocks": [1, 1, 1]}
    assert manifest["train_config"]["jointnet_epochs"] == 1
    assert not (model / "checkpoint").exists()
    est = PoseEstimator2D.load(model)
    assert est.jointnet is not None
    res = est.estimate([np.zeros((120, 80, 3), dtype=np.uint8)])
    assert bool(torch.isfinite(res.joints_2d).all())
