"""`ds3d train-2d --small` on real LSP data (ds3d.training.image2d): the model it writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from ds3d.cli import image2d as cli_image2d
from ds3d.cli import main as cli
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.facing import FacingNet
from ds3d.image2d.jointnet import JointNet
from ds3d.util.threads import intra_op_threads


@pytest.mark.usefixtures("data_dir")
def test_small_training_writes_a_loadable_model(small_model):
    manifest = json.loads((small_model / "manifest.json").read_text())
    assert manifest["seed"] == 3 and manifest["layers"] == ["forest1.pt.gz", "forest2.pt.gz"]
    assert "LSPet" in manifest["data"]["train"]
    est = PoseEstimator2D.load(small_model)
    assert [f.n_trees for f in est.layers] == [3, 3]
    assert est.layers[1].n_channels == 12 + 14  # the context layer reads layer-1 maps
    assert est.mixtures.n_components == 3
    assert not est.params.observer_labels
    # The joint network settles left and right: no facing CNN is trained beside it.
    assert isinstance(est.jointnet, JointNet) and est.facing is None
    assert manifest["train_seconds"]["jointnet"] > 0


@pytest.mark.slow
@pytest.mark.usefixtures("data_dir")
def test_without_a_joint_network_the_facing_cnn_is_trained(tmp_path, monkeypatch):
    monkeypatch.setitem(cli_image2d.SMALL, "jointnet_epochs", 0)
    assert cli(["train-2d", "--small", "--no-eval", "--out", str(tmp_path)]) == 0
    est = PoseEstimator2D.load(tmp_path)
    assert isinstance(est.facing, FacingNet) and est.jointnet is None
    res = est.estimate([np.random.default_rng(2).integers(0, 256, (150, 100, 3), dtype=np.uint8)])
    assert res.timings["jointnet"] == 0 and 0 <= float(res.facing_camera[0]) <= 1


@pytest.mark.slow
@pytest.mark.usefixtures("data_dir")
def test_observer_centric_model_trains_and_decides_facing(tmp_path):
    argv = ["train-2d", "--small", "--no-eval", "--observer-labels", "--out", str(tmp_path)]
    assert cli(argv) == 0
    est = PoseEstimator2D.load(tmp_path)
    assert est.params.observer_labels and isinstance(est.jointnet, JointNet)
    image = np.random.default_rng(2).integers(0, 256, (150, 100, 3), dtype=np.uint8)
    res = est.estimate([image, image[:, ::-1].copy()])
    assert res.facing_camera.shape == (2,)
    assert ((res.facing_camera >= 0) & (res.facing_camera <= 1)).all()


@pytest.mark.slow
@pytest.mark.usefixtures("data_dir")
@pytest.mark.parametrize(("sigma", "n_context"), [("6", 2 * 14), ("none", 14)])
def test_layer_2_reads_the_psm_pose_or_the_maps_alone(tmp_path, sigma, n_context):
    argv = ["train-2d", "--small", "--no-eval", "--set", f"context_pose_sigma={sigma}"]
    assert cli([*argv, "--out", str(tmp_path)]) == 0
    est = PoseEstimator2D.load(tmp_path)
    assert est.params.context_pose_sigma == (None if sigma == "none" else float(sigma))
    assert est.layers[1].n_channels == 12 + n_context  # image, layer-1 maps (pose heatmaps)
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in ((150, 90, 3), (120, 160, 3))]
    with intra_op_threads(1):  # one padded batch
        batch = est.estimate(images)
    for i, image in enumerate(images):  # the PSM in the context does not see the padding
        torch.testing.assert_close(est.estimate([image]).joints_2d[0], batch.joints_2d[i])
