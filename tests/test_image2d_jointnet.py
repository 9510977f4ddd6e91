"""The joint network (ds3d.image2d.jointnet): its training views, targets and grid mapping."""

import math

import pytest
import torch
from torch import nn

from ds3d.image2d import jointnet_train
from ds3d.image2d.estimator import EstimatorParams, left_right_hypotheses
from ds3d.image2d.jointnet import (
    MARGIN,
    STRIDE,
    JointNet,
    logits_on_grid,
    spatial_softmax,
)
from ds3d.image2d.jointnet_train import WINDOW, augment, jointnet_loss, soft_targets
from ds3d.image2d.psm import fit_pairwise_mixtures
from ds3d.skeleton import FLIP, NUM_JOINTS

# A standing person facing the camera, px (x, y), LSP order (as in test_psm).
STANDING_PX = [
    [22, 58], [22, 46], [23, 34], [31, 34], [32, 46], [32, 58],
    [12, 36], [14, 26], [20, 16], [34, 16], [40, 26], [42, 36],
    [27, 14], [27, 4],
]  # fmt: skip


def test_views_carry_their_joints_with_them():
    """A bright dot planted at joint 0 of a window lands where augment puts the joint, with the
    joint relabelled by FLIP in mirrored views."""
    torch.manual_seed(0)
    b = 32
    windows = torch.zeros(b, 3, WINDOW, WINDOW, dtype=torch.float16)
    joints = torch.full((b, NUM_JOINTS, 2), (WINDOW - 1) / 2)
    joints[:, 0] = torch.tensor([70.0, 100.0])
    windows[:, 0, 99:102, 69:72] = 1.0  # around (x, y) = (70, 100)
    views, pts, known = augment(windows, joints, torch.ones(b, NUM_JOINTS, dtype=torch.bool))
    mirrored = 0
    for k in range(b):
        lightness = views[k, 0]
        y, x = divmod(int(lightness.argmax()), lightness.shape[1])
        # Joint 0 (right ankle) becomes FLIP[0] (left ankle) in a mirrored view.
        label = 0 if known[k, 0] and math.dist(pts[k, 0].tolist(), (x, y)) < 1.5 else FLIP[0]
        assert math.dist(pts[k, label].tolist(), (x, y)) < 1.5, (k, pts[k, label], (x, y))
        mirrored += label != 0
    assert 0 < mirrored < b


def test_targets_are_distributions_peaked_at_the_joint_and_never_nan():
    joints = torch.tensor([[[4.0 * 5, 4.0 * 7], [1e4, 1e4]]])  # cell (5, 7); far off the grid
    t = soft_targets(joints, 16)
    assert t.shape == (1, 2, 256)
    torch.testing.assert_close(t[0, 0].sum(), torch.tensor(1.0))
    assert int(t[0, 0].argmax()) == 7 * 16 + 5
    assert not torch.isnan(t).any() and t[0, 1].sum() == 0


def test_loss_counts_only_masked_joints_and_learns():
    torch.manual_seed(0)
    logits = torch.zeros(2, NUM_JOINTS, 8, 8, requires_grad=True)
    joints = torch.full((2, NUM_JOINTS, 2), 12.0)
    mask = torch.zeros(2, NUM_JOINTS, dtype=torch.bool)
    mask[0, 3] = True
    loss = jointnet_loss(logits, joints, mask)
    torch.testing.assert_close(loss, torch.tensor(math.log(64.0)))  # uniform against any target
    loss.backward()
    grad = logits.grad
    assert grad[0, 3].abs().sum() > 0 and grad[1].abs().sum() == 0 and grad[0, 2].abs().sum() == 0
    assert grad[0, 3, 3, 3] < 0  # the joint's cell (12 / STRIDE = 3) is pushed up


class _Ramp(nn.Module):
    """Output cell (u, v) of channel c holds u + 100 v + c: where a grid cell reads from (u, v
    counted from the margin's corner)."""

    def forward(self, lab):
        b, _, h, w = lab.shape
        u = torch.arange(-(-w // STRIDE), dtype=torch.float32)
        v = torch.arange(-(-h // STRIDE), dtype=torch.float32)
        c = torch.arange(NUM_JOINTS, dtype=torch.float32)
        ramp = u[None, None, :] + 100 * v[None, :, None] + c[:, None, None]
        return ramp.expand(b, -1, -1, -1)


def test_grid_cells_read_the_output_cell_under_their_pixel():
    lab = torch.zeros(1, 3, 48, 40)
    grid = logits_on_grid(_Ramp(), lab, stride=3)
    assert grid.shape == (1, NUM_JOINTS, 16, 14)
    i, j = torch.meshgrid(torch.arange(16.0), torch.arange(14.0), indexing="ij")
    # Pixel (3 i, 3 j) is output cell ((3 i + MARGIN) / 4, (3 j + MARGIN) / 4) of the image in
    # its margin (48 + 2 MARGIN px high, 40 + 2 MARGIN wide).
    last_u, last_v = (40 + 2 * MARGIN) // STRIDE - 1, (48 + 2 * MARGIN) // STRIDE - 1
    want = ((3 * j + MARGIN) / STRIDE).clamp(max=last_u)
    want = want + 100 * ((3 * i + MARGIN) / STRIDE).clamp(max=last_v)
    torch.testing.assert_close(grid[0, 2], want + 2)


def test_spatial_softmax_is_a_distribution_over_the_cells():
    logits = torch.randn(2, NUM_JOINTS, 5, 6)
    probs = spatial_softmax(logits)
    torch.testing.assert_close(probs.sum((2, 3)), torch.ones(2, NUM_JOINTS))
    assert probs[0, 3].argmax() == logits[0, 3].argmax()


def test_network_output_is_a_quarter_of_the_input_rounded_up():
    net = JointNet().eval()
    with torch.no_grad():
        assert net(torch.zeros(1, 3, 50, 37)).shape == (1, NUM_JOINTS, 13, 10)


def test_training_lowers_the_loss_on_a_few_windows():
    torch.manual_seed(1)
    windows = torch.rand(8, 3, WINDOW, WINDOW).half()
    joints = torch.rand(8, NUM_JOINTS, 2) * 60 + 58
    for k in range(8):  # a bright blob marks the head top
        x, y = joints[k, 13].round().long().tolist()
        windows[k, 0, y - 3 : y + 4, x - 3 : x + 4] = 3.0
    located = torch.ones(8, NUM_JOINTS, dtype=torch.bool)
    before = _loss(JointNet().eval(), windows, joints, located)
    net = jointnet_train.train_jointnet(windows, joints, located, epochs=30, lr=3e-3, seed=0)
    assert _loss(net, windows, joints, located) < before - 0.5


def _loss(net, windows, joints, located):
    torch.manual_seed(5)
    views, pts, mask = augment(windows, joints, located)
    mask[:, :13] = False  # the head top alone has a cue
    with torch.no_grad():
        return float(jointnet_loss(net(views), pts, mask))


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
    _person_centric gives the network's."""
    flip = list(FLIP)
    pose = torch.tensor(STANDING_PX) + torch.tensor([4.0, 3.0])  # cells = px at stride 1
    poses = torch.stack([pose, pose[flip]])  # both labellings are poses a PSM must allow
    jitter = torch.randn(200, 2, NUM_JOINTS, 2, generator=torch.Generator().manual_seed(0))
    samples = (poses[None] + jitter).reshape(1, -1, NUM_JOINTS, 2)
    mixtures = fit_pairwise_mixtures(samples, n_components=2, seed=0)
    params = EstimatorParams(stride=1, jointnet_weight=1.0, unary_weight=1.0)
    forest = _peaks(pose, 70, 52)
    net = _peaks(pose if net_faces_camera else pose[flip], 70, 52)
    unaries, res, facing = left_right_hypotheses(forest, net, mixtures, params)
    assert bool(facing[0] > 0.5) == net_faces_camera
    torch.testing.assert_close(res.cells[0].float(), pose)  # the forests' labelling
    want = (forest + net if net_faces_camera else forest + net[:, flip]) / 2  # mean, w = 1
    torch.testing.assert_close(unaries, want)
