"""The 2D stage end to end: `ds3d train-2d --small` on real LSP data, then the estimator."""

import argparse
import json
import re
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ds3d.cli import field_overrides
from ds3d.errors import InvalidImage
from ds3d.image2d import commands, estimator
from ds3d.image2d.estimator import (
    LOG_EPS,
    Estimate2D,
    EstimatorParams,
    PoseEstimator2D,
    _person_centric,
    _traversal_groups,
    context_channels,
    layer_context,
    valid_cells,
)
from ds3d.image2d.facing import FacingNet
from ds3d.image2d.features import box_mean, image_channels, rgb_to_lab
from ds3d.image2d.jointnet import JointNet
from ds3d.image2d.psm import fit_pairwise_mixtures
from ds3d.image2d.train import faces_camera, observer_centric
from ds3d.paths import MODELS_DIR, data_root, project_relative
from ds3d.skeleton import FLIP
from ds3d.threads import intra_op_threads

needs_data = pytest.mark.skipif(
    not (data_root() / "lsp" / "joints.mat").is_file(), reason="LSP data not available"
)


def _cli(argv):
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command", required=True)
    evals = sub.add_parser("eval").add_subparsers(dest="what", required=True)
    benches = sub.add_parser("bench").add_subparsers(dest="what", required=True)
    commands.register(sub, evals, benches)
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    out = tmp_path_factory.mktemp("image2d")
    assert _cli(["train-2d", "--small", "--no-eval", "--out", str(out), "--seed", "3"]) == 0
    return out


def test_lab_of_known_colours():
    rgb = torch.tensor([[[255, 255, 255], [0, 0, 0], [255, 0, 0]]], dtype=torch.uint8)
    lab = rgb_to_lab(rgb.permute(2, 0, 1)[None].reshape(1, 3, 1, 3))[0, :, 0].T
    np.testing.assert_allclose(lab[0], [100, 0, 0], atol=0.05)
    np.testing.assert_allclose(lab[1], [0, 0, 0], atol=0.05)
    np.testing.assert_allclose(lab[2], [53.24, 80.09, 67.20], atol=0.1)


def test_channels_see_edges_and_their_orientation():
    img = np.zeros((1, 20, 20, 3), dtype=np.uint8)
    img[:, :, 10:] = 255  # a vertical edge: horizontal gradient, orientation bin 0
    ch = image_channels(torch.from_numpy(img))
    assert ch.shape == (1, 12, 20, 20)
    assert ch[0, 3, 10, 9] > 0.3 and ch[0, 3, 10, 2] == 0
    assert ch[0, 4:, 10, 9].argmax() == 0


def test_box_mean_is_a_zero_padded_box_filter():
    x = torch.rand(2, 3, 11, 8, dtype=torch.float64)
    want = F.avg_pool2d(x, 5, stride=1, padding=2, count_include_pad=True)
    torch.testing.assert_close(box_mean(x, 2), want)


def test_context_channels_and_valid_cells_follow_the_grid():
    probs = torch.arange(6.0).reshape(1, 1, 2, 3).expand(1, 14, 2, 3)
    ctx = context_channels(probs, stride=3, height=5, width=8)
    assert ctx.shape == (1, 14, 5, 8)
    # pixel (y, x) reads the nearest grid cell (y / 3, x / 3)
    assert ctx[0, 0, 0, 0] == 0 and ctx[0, 0, 0, 4] == 1 and ctx[0, 0, 4, 7] == 5
    valid = valid_cells([(5, 8), (2, 4)], 5, 8, 3)
    assert valid.shape == (2, 1, 2, 3)
    assert valid[0].all() and valid[1, 0].tolist() == [[True, True, False], [False, False, False]]
    # In a zero-padded batch each image reads only its own cells, as alone: a 6 px wide image
    # has cells 0-1, and its last pixel column reads cell 1 (not the batch's cell 2).
    maps = torch.rand(2, 14, 3, 4)
    sizes = [(7, 6), (9, 12)]
    batch = context_channels(maps, stride=3, height=9, width=12, sizes=sizes)
    for i, (h, w) in enumerate(sizes):
        gh, gw = -(-h // 3), -(-w // 3)
        alone = context_channels(maps[i : i + 1, :, :gh, :gw], stride=3, height=h, width=w)
        torch.testing.assert_close(batch[i : i + 1, :, :h, :w], alone)


@needs_data
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


@needs_data
def test_without_a_joint_network_the_facing_cnn_is_trained(tmp_path, monkeypatch):
    monkeypatch.setitem(commands.SMALL, "jointnet_epochs", 0)
    assert _cli(["train-2d", "--small", "--no-eval", "--out", str(tmp_path)]) == 0
    est = PoseEstimator2D.load(tmp_path)
    assert isinstance(est.facing, FacingNet) and est.jointnet is None
    res = est.estimate([np.random.default_rng(2).integers(0, 256, (150, 100, 3), dtype=np.uint8)])
    assert res.timings["jointnet"] == 0 and 0 <= float(res.facing_camera[0]) <= 1


@needs_data
def test_eval_lsp_on_held_out_train_images_with_an_override(small_model, tmp_path):
    out = tmp_path / "val.json"
    argv = ["lsp", "--model", str(small_model), "--split", "train", "--start", "990"]
    argv += ["--set", "n_scales=2", "--out", str(out)]
    assert _cli(["eval", *argv]) == 0
    report = json.loads(out.read_text())
    assert report["dataset"] == "LSP train im0991-im1000" and report["n_images"] == 10
    assert report["overrides"] == ["n_scales=2"]
    assert report["model"] == str(small_model)  # outside the project: as given
    assert project_relative(MODELS_DIR / "image2d") == "models/image2d"  # same on any checkout
    for name in ("psm", "unary_argmax"):
        assert 0 <= report[name]["pck@0.2"] <= 1 and len(report[name]["pck@0.2_per_joint"]) == 14
    overrides = ["observer_labels=false", "stride=4", "unary_weight=1.5", "select_stride=none"]
    assert field_overrides(EstimatorParams, overrides) == {
        "observer_labels": False,
        "stride": 4,
        "unary_weight": 1.5,
        "select_stride": None,
    }
    assert field_overrides(EstimatorParams, ["select_stride=6"]) == {"select_stride": 6}
    with pytest.raises(SystemExit, match=re.escape("is not a int | None")):
        field_overrides(EstimatorParams, ["select_stride=six"])
    with pytest.raises(SystemExit, match="not a EstimatorParams field"):
        _cli(["eval", "lsp", "--model", str(small_model), "--set", "n_scale=2"])
    with pytest.raises(SystemExit, match="is not a bool"):
        _cli(["eval", "lsp", "--model", str(small_model), "--set", "observer_labels=maybe"])


@needs_data
def test_observer_centric_model_trains_and_decides_facing(tmp_path):
    argv = ["train-2d", "--small", "--no-eval", "--observer-labels", "--out", str(tmp_path)]
    assert _cli(argv) == 0
    est = PoseEstimator2D.load(tmp_path)
    assert est.params.observer_labels and isinstance(est.jointnet, JointNet)
    image = np.random.default_rng(2).integers(0, 256, (150, 100, 3), dtype=np.uint8)
    res = est.estimate([image, image[:, ::-1].copy()])
    assert res.facing_camera.shape == (2,)
    assert ((res.facing_camera >= 0) & (res.facing_camera <= 1)).all()


def test_layer_context_adds_heatmaps_of_the_psm_pose_on_the_maps():
    # a planted pose: each joint's probability peaks at its own cell, so the PSM's MAP (on
    # these unaries, binaries fitted on the planted pose itself) puts every joint there
    gen = torch.Generator().manual_seed(0)
    cells = torch.stack([torch.randint(4, 30, (14,), generator=gen), torch.arange(14) * 2 + 3], -1)
    probs = torch.full((1, 15, 34, 34), 1e-3)
    probs[0, torch.arange(14), cells[:, 1], cells[:, 0]] = 0.9
    mixtures = fit_pairwise_mixtures(cells[None, None].float() * 3.0, n_components=1)
    # sigma 2 cells at stride 3; no blur of the unaries, so that each joint's peak is one cell
    params = EstimatorParams(context_pose_sigma=6.0, unary_blur=0)
    context = layer_context(probs, params, mixtures)
    assert context.shape == (1, 28, 34, 34)
    torch.testing.assert_close(context[:, :14], box_mean(probs[:, :14], params.context_blur))
    heat = context[0, 14:]
    assert torch.equal(heat.flatten(1).argmax(1), cells[:, 1] * 34 + cells[:, 0])
    assert heat.amax() == 1.0 and float(heat[0, cells[0, 1], cells[0, 0] + 2]) == pytest.approx(
        float(np.exp(-0.5))
    )
    without = layer_context(probs, replace(params, context_pose_sigma=None), None)
    torch.testing.assert_close(without, context[:, :14])


@needs_data
@pytest.mark.parametrize(("sigma", "n_context"), [("6", 2 * 14), ("none", 14)])
def test_layer_2_reads_the_psm_pose_or_the_maps_alone(tmp_path, sigma, n_context):
    argv = ["train-2d", "--small", "--no-eval", "--set", f"context_pose_sigma={sigma}"]
    assert _cli([*argv, "--out", str(tmp_path)]) == 0
    est = PoseEstimator2D.load(tmp_path)
    assert est.params.context_pose_sigma == (None if sigma == "none" else float(sigma))
    assert est.layers[1].n_channels == 12 + n_context  # image, layer-1 maps (pose heatmaps)
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in ((150, 90, 3), (120, 160, 3))]
    with intra_op_threads(1):  # one padded batch
        batch = est.estimate(images)
    for i, image in enumerate(images):  # the PSM in the context does not see the padding
        torch.testing.assert_close(est.estimate([image]).joints_2d[0], batch.joints_2d[i])


@needs_data
def test_estimate_batches_of_mixed_images_and_boxes(small_model):
    est = PoseEstimator2D.load(small_model)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in ((150, 90, 3), (240, 320, 3))]
    with intra_op_threads(1):  # one padded batch (more threads would split it)
        res = est.estimate(images, bboxes=[None, (100, 40, 160, 200)])
    assert res.joints_2d.shape == (2, 14, 2) and torch.isfinite(res.joints_2d).all()
    assert res.joint_scores.shape == (2, 14) and res.score.shape == (2,)
    assert res.unaries.shape[:2] == (2, 14) and (res.unaries <= 0).all()
    # each joint's score is its own unary at some cell (not the PSM's weighted unary)
    at_a_cell = torch.isclose(res.unaries.flatten(2), res.joint_scores[..., None]).any(-1)
    assert at_a_cell.all()
    assert set(res.timings) == {"features", "traversal", "jointnet", "psm", "total"}
    # each image alone gives the same pose and unaries as in the batch (padding does not leak,
    # not even into the cells at an image's right and bottom edges)
    for i in range(2):
        alone = est.estimate([images[i]], bboxes=[[None, (100, 40, 160, 200)][i]])
        torch.testing.assert_close(alone.joints_2d[0], res.joints_2d[i])
        h, w = alone.unaries.shape[-2:]
        torch.testing.assert_close(alone.unaries[0], res.unaries[i, :, :h, :w])
    # the box crop: joints land in the image, near the box
    assert (res.joints_2d[1, :, 0] > 20).all() and (res.joints_2d[1, :, 0] < 240).all()


@pytest.mark.parametrize("threads", [2, 3])
def test_threads_split_the_batch_without_changing_any_result(small_model, threads):
    est = PoseEstimator2D.load(small_model)
    rng = np.random.default_rng(5)
    shapes = ((150, 90, 3), (240, 320, 3), (120, 130, 3), (90, 160, 3), (200, 100, 3))
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in shapes]
    with intra_op_threads(1):
        one = est.estimate(images)
    with intra_op_threads(threads):
        split = est.estimate(images)
        assert torch.get_num_threads() == threads  # the caller's setting is left alone
    for name in ("joints_2d", "joint_scores", "score", "unaries", "map_to_image", "scale"):
        torch.testing.assert_close(getattr(split, name), getattr(one, name), rtol=0, atol=0)
    assert set(split.timings) == {"features", "traversal", "jointnet", "psm", "total"}


def test_traversal_groups_partition_the_batch_by_shape_within_the_budget():
    layer = SimpleNamespace(radius=40, n_channels=26)  # a context layer's padding and channels
    tall, wide = (135, 76), (76, 135)
    sizes = [tall, wide, tall, wide, tall, (135, 135)]
    groups = _traversal_groups(sizes, layer)
    assert sorted(i for g in groups for i in g) == list(range(len(sizes)))

    def nbytes(group):
        h = max(sizes[i][0] for i in group) + 80
        w = max(sizes[i][1] for i in group) + 80
        return len(group) * 4 * 27 * h * w

    assert all(len(g) == 1 or nbytes(g) <= estimator.GROUP_BYTES for g in groups)
    # by aspect ratio (height / width): the wide ones and the square, then the tall ones
    # (3.6 MB each padded; a fourth 215 x 215 px image would pass the 16 MB)
    assert groups == [[1, 3, 5], [0, 2, 4]]
    assert _traversal_groups([tall] * 3, SimpleNamespace(radius=400, n_channels=26)) == [
        [0],
        [1],
        [2],
    ]  # one image over the budget: a group of its own


def test_grouping_of_a_batch_changes_no_result(small_model, monkeypatch):
    est = PoseEstimator2D.load(small_model)
    rng = np.random.default_rng(6)
    shapes = ((150, 90, 3), (240, 320, 3), (120, 130, 3), (90, 160, 3), (200, 100, 3))
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in shapes]
    results = []
    with intra_op_threads(1):
        # one image per group; groups of 2-3 (4-6 MB per padded image here); all in one
        for budget in (0, 10 * 2**20, 2**40):
            monkeypatch.setattr(estimator, "GROUP_BYTES", budget)
            results.append(est.estimate(images))
    for res in results[:2]:
        for name in ("joints_2d", "joint_scores", "score", "unaries", "facing_camera"):
            expected = getattr(results[2], name)
            torch.testing.assert_close(getattr(res, name), expected, rtol=0, atol=0)


@needs_data
@pytest.mark.parametrize("coarse_trees, flip_test", [(None, False), (2, True)])
def test_coarse_pass_picks_the_scale_then_the_full_stride_answers(
    small_model, coarse_trees, flip_test
):
    est = PoseEstimator2D.load(small_model)
    est.params = replace(est.params, coarse_trees=coarse_trees, flip_test=flip_test)
    p = est.params
    assert (p.select_stride, p.stride, p.unary_blur) == (6, 3, 2)
    rng = np.random.default_rng(4)
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in ((150, 90, 3), (120, 200, 3))]
    res = est.estimate(images)
    # blur 2 cells of 3 px; the coarse pass never runs the flip test
    coarse = replace(p, stride=6, unary_blur=1, select_stride=None, flip_test=False)
    # The coarse pass reads the first coarse_trees trees of each layer (all with None).
    layers = [f.first_trees(coarse_trees or f.n_trees) for f in est.layers]
    coarse = PoseEstimator2D(layers, est.mixtures, coarse)
    for i, image in enumerate(images):
        scores = [coarse.estimate([image], scales=[s]).score.item() for s in est.scales()]
        chosen = est.scales()[int(np.argmax(scores))]
        fine = est.estimate([image], scales=[chosen])
        torch.testing.assert_close(fine.joints_2d[0], res.joints_2d[i])
        torch.testing.assert_close(fine.score[0], res.score[i])


@needs_data
def test_flip_test_makes_the_unaries_mirror_symmetric(small_model):
    est = PoseEstimator2D.load(small_model)
    # The flip test is the cascade's: the joint network's maps are not mirrored, so leave it out.
    est.params = replace(est.params, flip_test=True, jointnet_weight=0.0)
    # 135 px high: the base scale is 1, so the cascade sees the image as it is; (91 - 1) % 3 == 0:
    # the grid of the mirror image is the image's own, mirrored.
    image = np.random.default_rng(2).integers(0, 256, (135, 91, 3), dtype=np.uint8)
    unaries = est.estimate([image], scales=[1.0]).unaries[0]
    mirrored = est.estimate([image[:, ::-1].copy()], scales=[1.0]).unaries[0]
    assert unaries.shape == (14, 45, 31)
    # Probabilities, equal up to the rounding of the integral-image blur (features.box_mean).
    torch.testing.assert_close(
        mirrored.exp(), unaries[list(FLIP)].flip(-1).exp(), atol=1e-6, rtol=0
    )
    # Without it (the default) the cascade is not symmetric: the test has something to show.
    est.params = replace(est.params, flip_test=False)
    plain = est.estimate([image], scales=[1.0]).unaries[0].exp()
    plain_mirrored = est.estimate([image[:, ::-1].copy()], scales=[1.0]).unaries[0].exp()
    assert (plain_mirrored - plain[list(FLIP)].flip(-1)).abs().max() > 0.01


@needs_data
def test_joints_move_from_their_map_cells_to_the_local_centroid_only(small_model):
    est = PoseEstimator2D.load(small_model)
    image = np.random.default_rng(5).integers(0, 256, (160, 100, 3), dtype=np.uint8)
    est.params = replace(est.params, centroid_radius=None)
    on_grid = est.estimate([image])
    est.params = replace(est.params, centroid_radius=2)
    moved = est.estimate([image])
    # The centroid changes neither the MAP nor its score, nor the chosen scale.
    torch.testing.assert_close(moved.score, on_grid.score)
    torch.testing.assert_close(moved.map_to_image, on_grid.map_to_image)

    def to_cells(est2d):  # image px -> unary cells (u, v)
        a = torch.diagonal(est2d.map_to_image[0, :, :2])
        return (est2d.joints_2d[0] - est2d.map_to_image[0, :, 2]) / a

    cells = to_cells(on_grid)
    torch.testing.assert_close(cells, cells.round(), atol=1e-4, rtol=0)  # MAP: on the grid
    shift = (to_cells(moved) - cells).norm(dim=-1)
    assert bool((shift <= 6**0.5 + 1e-4).all()) and bool((shift > 1e-3).any())


@needs_data
def test_sample_unaries_reads_the_maps_at_image_points(small_model):
    est = PoseEstimator2D.load(small_model)
    image = np.random.default_rng(1).integers(0, 256, (160, 100, 3), dtype=np.uint8)
    res = est.estimate([image])
    # image points of a few cells, through map_to_image
    cells = torch.tensor([[2.0, 3.0], [5.0, 1.0], [0.0, 0.0]])
    uv1 = torch.cat([cells, torch.ones(3, 1)], 1)
    points = (res.map_to_image[0] @ uv1.T).T  # (3, 2)
    sampled = res.sample_unaries(points[None, :, None, :].expand(1, 3, 14, 2))  # (1, 3, 14)
    for k, (u, v) in enumerate(cells.long().tolist()):
        torch.testing.assert_close(sampled[0, k], res.unaries[0, :, v, u])
    far = res.sample_unaries(torch.full((1, 1, 14, 2), -500.0))
    torch.testing.assert_close(far, torch.full((1, 1, 14), float(np.log(LOG_EPS))))


def test_estimate_rejects_bad_inputs():
    est = PoseEstimator2D([], None, EstimatorParams())
    with pytest.raises(ValueError):
        est.estimate([])
    with pytest.raises(InvalidImage):
        est.estimate([np.zeros((10, 10), dtype=np.uint8)])
    with pytest.raises(ValueError):
        est.estimate([np.zeros((10, 10, 3), dtype=np.uint8)], bboxes=[(5, 5, 2, 2)])


def test_observer_centric_labels_follow_the_image_sides():
    joints = np.zeros((14, 2), dtype=np.float32)
    joints[:, 0] = np.arange(14)  # distinct x per joint
    joints[8, 0], joints[9, 0] = 50, 40  # right shoulder right of the left: faces away
    joints[2, 0], joints[3, 0] = 10, 20  # hips as if facing the camera
    visible = np.arange(14) % 2 == 0
    assert not faces_camera(joints)
    obs, vis = observer_centric(joints, visible)
    arm_r, arm_l = [6, 7, 8], [11, 10, 9]
    np.testing.assert_array_equal(obs[arm_r], joints[arm_l])  # arms swapped
    np.testing.assert_array_equal(vis[arm_l], visible[arm_r])
    np.testing.assert_array_equal(obs[:6], joints[:6])  # legs kept
    assert faces_camera(obs)
    again, _ = observer_centric(obs, vis)
    np.testing.assert_array_equal(again, obs)


def test_faces_away_swaps_left_and_right_at_the_end():
    est = Estimate2D(
        torch.arange(2 * 14 * 2, dtype=torch.float32).reshape(2, 14, 2),
        torch.arange(28, dtype=torch.float32).reshape(2, 14),
        torch.zeros(2),
        torch.arange(2 * 14 * 4, dtype=torch.float32).reshape(2, 14, 2, 2),
        torch.zeros(2, 2, 3),
        torch.ones(2),
        torch.tensor([0.9, 0.2]),
    )
    out = _person_centric(est)
    flip = list(FLIP)
    torch.testing.assert_close(out.joints_2d[0], est.joints_2d[0])
    torch.testing.assert_close(out.joints_2d[1], est.joints_2d[1, flip])
    torch.testing.assert_close(out.joint_scores[1], est.joint_scores[1, flip])
    torch.testing.assert_close(out.unaries[1], est.unaries[1, flip])
