"""The 2D estimator end to end on a small model trained here (ds3d.image2d.estimator)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ds3d.image2d.estimator import PoseEstimator2D, nearest_scale
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.result import LOG_EPS
from ds3d.skeleton import FLIP
from ds3d.util.threads import intra_op_threads


@pytest.mark.usefixtures("data_dir")
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


def test_grouping_of_a_batch_changes_no_result(small_model, monkeypatch):
    est = PoseEstimator2D.load(small_model)
    rng = np.random.default_rng(6)
    shapes = ((150, 90, 3), (240, 320, 3), (120, 130, 3), (90, 160, 3), (200, 100, 3))
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in shapes]
    results = []
    with intra_op_threads(1):
        # one image per group; groups of 2-3 (4-6 MB per padded image here); all in one
        for budget in (0, 10 * 2**20, 2**40):
            monkeypatch.setattr(PoseEstimator2D, "_group_bytes", budget)
            results.append(est.estimate(images))
    for res in results[:2]:
        for name in ("joints_2d", "joint_scores", "unaries"):
            expected = getattr(results[2], name)
            torch.testing.assert_close(getattr(res, name), expected, rtol=0, atol=0)
        # sums over the group's padded grid, whose size changes their float summation order
        for name in ("score", "facing_camera"):
            expected = getattr(results[2], name)
            torch.testing.assert_close(getattr(res, name), expected, rtol=1e-4, atol=0)


@pytest.mark.usefixtures("data_dir")
@pytest.mark.parametrize("coarse_trees, flip_test", [(None, False), (2, True)])
def test_coarse_pass_picks_the_scale_then_the_full_stride_answers(
    small_model, coarse_trees, flip_test
):
    est = PoseEstimator2D.load(small_model)
    est.params = est.params.with_inference(
        scale_choice="coarse", coarse_trees=coarse_trees, flip_test=flip_test
    )
    p = est.params
    assert (p.select_stride, p.stride, p.unary_blur) == (6, 3, 2)
    rng = np.random.default_rng(4)
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in ((150, 90, 3), (120, 200, 3))]
    res = est.estimate(images)
    # blur 2 cells of 3 px; the coarse pass never runs the flip test
    coarse = replace(p, stride=6, unary_blur=1, flip_test=False)
    # The coarse pass reads the first coarse_trees trees of each layer (all with None).
    layers = [f.first_trees(coarse_trees or f.n_trees) for f in est.layers]
    coarse = PoseEstimator2D(layers, est.mixtures, coarse)
    for i, image in enumerate(images):
        scores = [coarse.estimate([image], scales=[s]).score.item() for s in est.scales()]
        chosen = est.scales()[int(np.argmax(scores))]
        fine = est.estimate([image], scales=[chosen])
        torch.testing.assert_close(fine.joints_2d[0], res.joints_2d[i])
        torch.testing.assert_close(fine.score[0], res.score[i])


@pytest.mark.usefixtures("data_dir")
@pytest.mark.parametrize("flip_test", [False, True])
def test_the_network_picks_the_scale_then_the_full_pass_answers(small_model, flip_test):
    est = PoseEstimator2D.load(small_model)
    est.params = est.params.with_inference(flip_test=flip_test)
    assert est.params.scale_choice == "network"
    rng = np.random.default_rng(4)
    shapes = ((150, 90, 3), (120, 200, 3), (90, 60, 3))
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in shapes]
    res = est.estimate(images)
    for i, image in enumerate(images):
        # the scale it ran at: working px per image px over the base scale of the whole image
        base = est.params.canonical_extent * est.params.image_to_extent / max(image.shape[:2])
        chosen = min(est.scales(), key=lambda s: abs(math.log(s * base / res.scale[i])))
        alone = est.estimate([image], scales=[chosen])
        torch.testing.assert_close(alone.joints_2d[0], res.joints_2d[i])
        torch.testing.assert_close(
            alone.unaries[0], res.unaries[i, :, : alone.unaries.shape[2], : alone.unaries.shape[3]]
        )


def test_nearest_scale_is_nearest_in_ratio():
    scales = [1.2, 1.0, 0.8]
    wanted = torch.tensor([1.5, 1.09, 1.1, 0.89, 0.9, 0.1, 0.0])
    assert nearest_scale(wanted, scales).tolist() == [0, 1, 0, 2, 1, 2, 2]


@pytest.mark.usefixtures("data_dir")
def test_flip_test_makes_the_unaries_mirror_symmetric(small_model):
    est = PoseEstimator2D.load(small_model)
    # The flip test is the cascade's: the joint network's maps are not mirrored, so leave it out.
    est.params = replace(est.params, flip_test=True, jointnet_weight=0.0)
    # 135 px high: the base scale is 1, so the cascade sees the image as it is; (91 - 1) % 3 == 0:
    # the grid of the mirror image is the image's own, mirrored.
    image = np.random.default_rng(2).integers(0, 256, (135, 91, 3), dtype=np.uint8)
    # The image's own cells of the maps (past them, the padding to a size bucket).
    unaries = est.estimate([image], scales=[1.0]).unaries[0, :, :45, :31]
    mirrored = est.estimate([image[:, ::-1].copy()], scales=[1.0]).unaries[0, :, :45, :31]
    # Probabilities, equal up to the rounding of the integral-image blur (features.box_mean).
    torch.testing.assert_close(
        mirrored.exp(), unaries[list(FLIP)].flip(-1).exp(), atol=1e-6, rtol=0
    )
    # Without it (the default) the cascade is not symmetric: the test has something to show.
    est.params = replace(est.params, flip_test=False)
    plain = est.estimate([image], scales=[1.0]).unaries[0, :, :45, :31].exp()
    plain_mirrored = est.estimate([image[:, ::-1].copy()], scales=[1.0]).unaries[0, :, :45, :31]
    plain_mirrored = plain_mirrored.exp()
    assert (plain_mirrored - plain[list(FLIP)].flip(-1)).abs().max() > 0.01


@pytest.mark.usefixtures("data_dir")
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


@pytest.mark.usefixtures("data_dir")
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


def test_estimate_of_no_images_is_refused():
    """The images themselves are checked where they enter (tests/test_inputs.py)."""
    est = PoseEstimator2D([], None, EstimatorParams())
    with pytest.raises(ValueError, match="no images"):
        est.estimate([])


@pytest.mark.usefixtures("data_dir")
def test_an_estimator_moved_to_a_device_answers_alike(small_model):
    """PoseEstimator2D.to moves every part of the model (here to the CPU it is on, as a GPU
    machine's check does to CUDA: tests/test_pipeline.py) and answers alike."""
    est = PoseEstimator2D.load(small_model)
    moved = est.to("cpu")
    assert moved is not est and moved.device.type == "cpu"
    assert all(f.node_table.device.type == "cpu" for f in moved.layers)
    rng = np.random.default_rng(2)
    images = [rng.integers(0, 256, s, dtype=np.uint8) for s in ((150, 90, 3), (200, 260, 3))]
    with intra_op_threads(1):
        for name in ("joints_2d", "score", "unaries"):
            torch.testing.assert_close(
                getattr(moved.estimate(images), name), getattr(est.estimate(images), name)
            )
