"""The forest cascade's grid, context and batching (ds3d.image2d.cascade)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ds3d.image2d import cascade
from ds3d.image2d.cascade import context_channels, layer_context, traversal_groups, valid_cells
from ds3d.image2d.features import box_mean
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import fit_pairwise_mixtures
from ds3d.image2d.result import LOG_EPS


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


def test_traversal_groups_partition_the_batch_by_shape_within_the_budget():
    layer = SimpleNamespace(radius=40, n_channels=26)  # a context layer's padding and channels
    tall, wide = (135, 76), (76, 135)
    sizes = [tall, wide, tall, wide, tall, (135, 135)]
    groups = traversal_groups(sizes, layer)
    assert sorted(i for g in groups for i in g) == list(range(len(sizes)))

    def nbytes(group):
        h = max(sizes[i][0] for i in group) + 80
        w = max(sizes[i][1] for i in group) + 80
        return len(group) * 4 * 27 * h * w

    assert all(len(g) == 1 or nbytes(g) <= cascade.GROUP_BYTES for g in groups)
    # by aspect ratio (height / width): the wide ones and the square, then the tall ones
    # (3.6 MB each padded; a fourth 215 x 215 px image would pass the 16 MB)
    assert groups == [[1, 3, 5], [0, 2, 4]]
    assert traversal_groups([tall] * 3, SimpleNamespace(radius=400, n_channels=26)) == [
        [0],
        [1],
        [2],
    ]  # one image over the budget: a group of its own


def test_forest_cells_are_those_where_some_joint_is_near_its_best():
    probs = torch.zeros(1, 14, 6, 8)
    probs[0, 2:, 1, 2] = 1.0  # joints 2-13 sure of one cell
    probs[0, 0, 1, 2] = 0.5  # joint 0's best; 0.1 is within 3 nats of it (e^-3 = 0.05), 0.02 not
    probs[0, 0, 4, 6], probs[0, 0, 5, 7] = 0.1, 0.02
    probs[0, 1] = 1 / 48  # a flat map: every cell is its best
    cells = cascade.forest_cells(torch.log(probs + LOG_EPS), reach=3.0)
    assert cells.all()
    probs[0, 1] = 0.0
    probs[0, 1, 0, 0] = 1e-3  # a map next to nothing: its best cell still counts
    cells = cascade.forest_cells(torch.log(probs + LOG_EPS), reach=3.0)
    assert sorted(map(tuple, cells[0].nonzero().tolist())) == [(0, 0), (1, 2), (4, 6)]


@pytest.mark.usefixtures("data_dir")
def test_the_forests_run_on_the_chosen_cells_alone(small_model):
    from ds3d.image2d.estimator import PoseEstimator2D

    est = PoseEstimator2D.load(small_model)
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, shape, dtype=np.uint8) for shape in ((120, 90, 3), (96, 60, 3))]
    channels, sizes = cascade.group_channels(images, {"features": 0.0})
    dense = cascade.cascade_probs(est.layers, channels, est.params, sizes)
    gh, gw = dense[0].shape[-2:]
    every = torch.ones(2, gh, gw, dtype=torch.bool)
    everywhere = cascade.cascade_probs(est.layers, channels, est.params, sizes, cells=every)
    for a, b in zip(dense, everywhere, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    cells = torch.zeros(2, gh, gw, dtype=torch.bool)
    cells[0, 5:15, 3:12] = True  # the second image chose none
    first, last = cascade.cascade_probs(est.layers, channels, est.params, sizes, cells=cells)
    # The first layer reads the image alone: on the chosen cells it finds what it finds on all.
    torch.testing.assert_close(first[0][:, cells[0]], dense[0][0][:, cells[0]], rtol=0, atol=0)
    assert not first[0][:, ~cells[0]].any() and not last[0][:, ~cells[0]].any()
    # The later layer reads its context from the chosen cells alone: it differs somewhere.
    assert not torch.equal(last[0][:, cells[0]], dense[1][0][:, cells[0]])
    assert last[1].count_nonzero() <= 15  # at most its one stand-in cell
