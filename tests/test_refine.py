"""The 2D refinement (ds3d.refine): its search window and its PSMs."""

from __future__ import annotations

import numpy as np
import torch

from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.result import LOG_EPS, Estimate2D
from ds3d.refine import RefineParams, refine, search_window
from ds3d.skeleton import NUM_JOINTS
from ds3d.util.threads import intra_op_threads


def test_search_window_reads_cells_and_pads_beyond_the_grid():
    unaries = torch.arange(4 * 5, dtype=torch.float32).view(1, 4, 5).expand(NUM_JOINTS, 4, 5)
    cells = torch.tensor([[1.2, 0.5], [3.0, 2.0]]).repeat(NUM_JOINTS // 2, 1)[None]  # (1, 14, 2)
    window, origin = search_window(unaries, cells, margin=1)
    assert origin.tolist() == [0, -1]  # u from floor(1.2) - 1, v from floor(0.5) - 1
    assert window.shape == (NUM_JOINTS, 5, 5)  # v -1..3, u 0..4
    assert bool((window[:, 0] == np.log(LOG_EPS)).all())  # row v = -1 lies above the grid
    torch.testing.assert_close(window[:, 1:], unaries[:, 0:4, 0:5])
    # projections far off the image: the window stays within the margin of the grid
    far = torch.tensor([[-500.0, 2.0], [900.0, 3.0]]).repeat(NUM_JOINTS // 2, 1)[None]
    window, origin = search_window(unaries, far, margin=1)
    assert origin.tolist() == [-1, 1] and window.shape == (NUM_JOINTS, 4, 7)  # v 1..4, u -1..5


def test_refinement_keeps_weak_joints_on_the_grid():
    # Every cell of a 10 x 10 grid has p = 0.05; the neighbours put half the joints 3 cells
    # left of it. Weighted by 4, an in-grid cell costs 4 log 0.05 = -12; a cell beyond the grid
    # must cost 4 log(LOG_EPS) = -37 (the grid's floor, weighted alike), so the MAP stays on
    # the grid, one binary step from the neighbours.
    unaries = torch.full((1, NUM_JOINTS, 10, 10), float(np.log(0.05)))
    identity = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])  # cell (u, v) = pixel (x, y)
    one = torch.ones(1)
    estimate = Estimate2D(
        torch.zeros(1, NUM_JOINTS, 2), torch.zeros(1, NUM_JOINTS), one, unaries, identity, one, one
    )
    pose = torch.stack(
        [torch.arange(NUM_JOINTS) % 2 * 5.0 - 3.0, torch.arange(NUM_JOINTS) * 0.6], -1
    )
    jitter = 0.3 * torch.randn(32, NUM_JOINTS, 2, generator=torch.Generator().manual_seed(0))
    neighbours = (pose + jitter)[None, None]  # (1, 1, 32, 14, 2)
    params, config = EstimatorParams(unary_weight=4.0), RefineParams(unary_weight=1.0)
    ref = refine(estimate, params, neighbours, torch.ones(1, 1, 32), config)
    joints = ref.joints_2d[0, 0]
    assert bool((joints >= 0).all() & (joints <= 9).all()), joints


def test_refinement_on_two_threads_equals_one_thread():
    # refine splits the images across threads (ds3d.util.threads); its result must not depend on it
    gen = torch.Generator().manual_seed(1)
    b, s, n = 3, 2, 16
    logits = torch.randn(b, NUM_JOINTS, 12 * 10, generator=gen)
    unaries = torch.log_softmax(logits, -1).view(b, NUM_JOINTS, 12, 10)
    identity = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]]).expand(b, -1, -1)
    ones = torch.ones(b)
    estimate = Estimate2D(
        torch.zeros(b, NUM_JOINTS, 2),
        torch.zeros(b, NUM_JOINTS),
        ones,
        unaries,
        identity,
        ones,
        ones,
    )
    pose = torch.rand(NUM_JOINTS, 2, generator=gen) * torch.tensor([9.0, 11.0])
    neighbours = pose + 0.7 * torch.randn(b, s, n, NUM_JOINTS, 2, generator=gen)
    weights = torch.rand(b, s, n, generator=gen)
    runs = []
    for threads in (1, 2):
        with intra_op_threads(threads):
            runs.append(refine(estimate, EstimatorParams(), neighbours, weights, RefineParams()))
    assert not torch.equal(runs[0].joints_2d[0], runs[0].joints_2d[2])  # the images differ
    assert torch.equal(runs[0].joints_2d, runs[1].joints_2d)
    assert torch.equal(runs[0].score, runs[1].score)
