"""Left and right (ds3d.image2d.left_right): the PSM under both labellings, the swap at the end."""

from __future__ import annotations

import pytest
import torch

from ds3d.image2d.left_right import person_centric, settle_left_right
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import fit_pairwise_mixtures
from ds3d.image2d.result import Estimate2D
from ds3d.skeleton import FLIP, NUM_JOINTS

# A standing person facing the camera, px (x, y), LSP order (as in test_psm).
STANDING_PX = [
    [22, 58], [22, 46], [23, 34], [31, 34], [32, 46], [32, 58],
    [12, 36], [14, 26], [20, 16], [34, 16], [40, 26], [42, 36],
    [27, 14], [27, 4],
]  # fmt: skip


def _peaks(cells: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(14, 2) cells (x, y) -> (1, 14, height, width) log unaries peaked at them."""
    ys = torch.arange(height, dtype=torch.float32)[:, None]
    xs = torch.arange(width, dtype=torch.float32)[None, :]
    d2 = (xs - cells[:, 0, None, None]) ** 2 + (ys - cells[:, 1, None, None]) ** 2
    return torch.log(torch.exp(-0.5 * d2) + 1e-4)[None]


@pytest.mark.parametrize("net_faces_camera", [True, False])
def test_hypotheses_take_left_and_right_from_the_network(net_faces_camera):
    """The forests' maps put joint j at P[j] (everyone faces the camera); the network agrees,
    or puts joint j at P[FLIP[j]] (the person faces away). The PSM under both labellings of
    the forests' maps follows the network, and answers in the forests' labelling, so that
    person_centric gives the network's."""
    flip = list(FLIP)
    pose = torch.tensor(STANDING_PX) + torch.tensor([4.0, 3.0])  # cells = px at stride 1
    poses = torch.stack([pose, pose[flip]])  # both labellings are poses a PSM must allow
    jitter = torch.randn(200, 2, NUM_JOINTS, 2, generator=torch.Generator().manual_seed(0))
    samples = (poses[None] + jitter).reshape(1, -1, NUM_JOINTS, 2)
    mixtures = fit_pairwise_mixtures(samples, n_components=2, seed=0)
    params = EstimatorParams(stride=1, jointnet_weight=1.0, unary_weight=1.0)
    forest = _peaks(pose, 70, 52)
    net = _peaks(pose if net_faces_camera else pose[flip], 70, 52)
    unaries, res, facing = settle_left_right(forest, net, mixtures, params)
    assert bool(facing[0] > 0.5) == net_faces_camera
    torch.testing.assert_close(res.cells[0].float(), pose)  # the forests' labelling
    want = (forest + net if net_faces_camera else forest + net[:, flip]) / 2  # mean, w = 1
    torch.testing.assert_close(unaries, want)


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
    out = person_centric(est)
    flip = list(FLIP)
    torch.testing.assert_close(out.joints_2d[0], est.joints_2d[0])
    torch.testing.assert_close(out.joints_2d[1], est.joints_2d[1, flip])
    torch.testing.assert_close(out.joint_scores[1], est.joint_scores[1, flip])
    torch.testing.assert_close(out.unaries[1], est.unaries[1, flip])
