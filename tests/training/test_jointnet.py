"""Training of the joint network (ds3d.training.jointnet): its views, targets and loss."""

from __future__ import annotations

import math

import pytest
import torch

from ds3d.image2d.jointnet import JointNet, JointNetShape
from ds3d.skeleton import FLIP, NUM_JOINTS
from ds3d.training import jointnet as jointnet_training
from ds3d.training.jointnet import (
    CROP,
    WINDOW,
    augment,
    edge_cut,
    jointnet_loss,
    low_resolution,
    occlude,
    soft_targets,
    view_windows,
)


def test_views_carry_their_joints_with_them():
    """A bright dot planted at joint 0 of a window lands where view_windows puts the joint, with
    the joint relabelled by FLIP in mirrored views."""
    torch.manual_seed(0)
    b = 32
    windows = torch.zeros(b, 3, WINDOW, WINDOW, dtype=torch.float16)
    joints = torch.full((b, NUM_JOINTS, 2), (WINDOW - 1) / 2)
    joints[:, 0] = torch.tensor([70.0, 100.0])
    windows[:, 0, 99:102, 69:72] = 1.0  # around (x, y) = (70, 100)
    views, pts, known = view_windows(windows, joints, torch.ones(b, NUM_JOINTS, dtype=torch.bool))
    mirrored = 0
    for k in range(b):
        # where the dot went: the centroid of the lightness above the view's background
        weight = views[k, 0] - views[k, 0].min()
        ys, xs = torch.meshgrid(
            *(torch.arange(n, dtype=torch.float32) for n in weight.shape), indexing="ij"
        )
        x, y = float((weight * xs).sum() / weight.sum()), float((weight * ys).sum() / weight.sum())
        # Joint 0 (right ankle) becomes FLIP[0] (left ankle) in a mirrored view.
        label = 0 if known[k, 0] and math.dist(pts[k, 0].tolist(), (x, y)) < 1 else FLIP[0]
        assert math.dist(pts[k, label].tolist(), (x, y)) < 1, (k, pts[k, label], (x, y))
        mirrored += label != 0
    assert 0 < mirrored < b


def test_an_edge_cut_blanks_one_band_beyond_which_lies_a_share_of_the_person():
    """Every chosen view loses the pixels beyond one edge, which leaves 10-40 % of its joints'
    extent along that axis beyond it (those joints stay targets: the network learns where they
    lie); the others keep every pixel."""
    torch.manual_seed(3)
    b = 64
    views = torch.rand(b, 3, CROP, CROP) + 0.5  # no zeros of its own
    joints = torch.rand(b, NUM_JOINTS, 2) * 80 + 20
    known = torch.ones(b, NUM_JOINTS, dtype=torch.bool)
    chosen = torch.arange(b) % 2 == 0
    cut = edge_cut(views.clone(), joints, known, chosen)
    blank = (cut == 0).all(1)  # (b, H, W)
    assert not blank[~chosen].any()
    for k in torch.nonzero(chosen).view(-1).tolist():
        rows, cols = blank[k].all(1), blank[k].all(0)  # whole rows (top / bottom) or columns
        axis = 1 if rows.any() else 0
        lines = rows if axis else cols
        assert lines.any() and blank[k].sum() == lines.sum() * CROP  # one band, nothing else
        coord = joints[k, :, axis]
        edge = torch.nonzero(lines).view(-1)
        low, high = float(coord.min()), float(coord.max())
        # the band runs from the view's border to the cut, 10-40 % of the extent inside the
        # joints' span (to the px the band's lines round it to)
        if int(edge.min()) == 0:
            depth = float(edge.max() + 1) - low
        else:
            depth = high - float(edge.min())
        extent = high - low
        assert 0.1 * extent - 1 <= depth <= 0.4 * extent + 1


def test_an_occluder_is_one_rectangle_of_another_view():
    torch.manual_seed(4)
    b = 16
    views = torch.arange(b, dtype=torch.float32)[:, None, None, None].expand(b, 3, CROP, CROP)
    chosen = torch.arange(b) < 8
    out = occlude(views.clone(), chosen)
    for k in range(b):
        changed = (out[k] != views[k]).any(0)
        if not chosen[k]:
            assert not changed.any()
            continue
        ys, xs = torch.nonzero(changed, as_tuple=True)
        if len(ys) == 0:  # the other view drawn was itself
            continue
        box = changed[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
        assert box.all()  # one filled rectangle
        side = torch.tensor([ys.max() - ys.min() + 1, xs.max() - xs.min() + 1]) / CROP
        assert (side >= 0.15 - 2 / CROP).all() and (side <= 0.4 + 2 / CROP).all()
        assert len(out[k][:, changed].unique()) == 1  # all of it from one other view


def test_low_resolution_keeps_the_mean_and_loses_the_detail():
    torch.manual_seed(5)
    views = torch.rand(4, 3, CROP, CROP)
    chosen = torch.tensor([True, False, True, False])
    out = low_resolution(views.clone(), chosen)
    torch.testing.assert_close(out[~chosen], views[~chosen], rtol=0, atol=0)
    assert (out[chosen].mean((1, 2, 3)) - views[chosen].mean((1, 2, 3))).abs().max() < 0.01
    detail = (out[chosen].diff(dim=-1).abs().mean()) / views[chosen].diff(dim=-1).abs().mean()
    assert detail < 0.6


def test_augment_keeps_known_joints_inside_the_view():
    torch.manual_seed(6)
    b = 64
    windows = torch.rand(b, 3, WINDOW, WINDOW).half()
    joints = torch.rand(b, NUM_JOINTS, 2) * 100 + 38
    views, pts, known = augment(windows, joints, torch.ones(b, NUM_JOINTS, dtype=torch.bool))
    assert views.shape == (b, 3, CROP, CROP) and not torch.isnan(views).any()
    inside = ((pts >= 0) & (pts <= CROP - 1)).all(-1)
    assert (inside | ~known).all() and known.float().mean() > 0.5


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


@pytest.mark.slow
def test_training_lowers_the_loss_on_a_few_windows():
    torch.manual_seed(1)
    windows = torch.rand(8, 3, WINDOW, WINDOW).half()
    joints = torch.rand(8, NUM_JOINTS, 2) * 60 + 58
    for k in range(8):  # a bright blob marks the head top
        x, y = joints[k, 13].round().long().tolist()
        windows[k, 0, y - 3 : y + 4, x - 3 : x + 4] = 3.0
    located = torch.ones(8, NUM_JOINTS, dtype=torch.bool)
    before = _loss(JointNet().eval(), windows, joints, located)
    net, seconds = jointnet_training.train_jointnet(
        windows, joints, located, epochs=30, lr=3e-3, seed=0
    )
    assert _loss(net, windows, joints, located) < before - 0.5 and seconds > 0


def _six_windows(seed: int) -> tuple[tuple, JointNetShape]:
    """Six random training windows, their joints and located flags, and a tiny network's
    shape: train_jointnet's arguments for a run of seconds."""
    torch.manual_seed(seed)
    data = (
        torch.rand(6, 3, WINDOW, WINDOW).half(),
        torch.rand(6, NUM_JOINTS, 2) * 60 + 58,
        torch.ones(6, NUM_JOINTS, dtype=torch.bool),
    )
    return data, JointNetShape((8, 8, 8), (0, 1, 1))


def test_a_resumed_training_ends_where_an_uninterrupted_one_does(tmp_path, monkeypatch):
    data, shape = _six_windows(2)
    whole, _ = jointnet_training.train_jointnet(*data, 3, 3e-3, 0, shape)
    checkpoint = tmp_path / "jointnet.pt"
    jointnet_training.train_jointnet(*data, 1, 3e-3, 0, shape, checkpoint)
    with pytest.raises(ValueError, match="another training"):  # 1 epoch of 1 is not 1 of 3
        jointnet_training.train_jointnet(*data, 3, 3e-3, 0, shape, checkpoint)
    checkpoint.unlink()
    # A run killed in its second epoch (one batch per epoch here), then resumed.
    calls = []

    def loss_until_killed(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return jointnet_loss(*args)

    monkeypatch.setattr(jointnet_training, "jointnet_loss", loss_until_killed)
    with pytest.raises(KeyboardInterrupt):
        jointnet_training.train_jointnet(*data, 3, 3e-3, 0, shape, checkpoint)
    monkeypatch.undo()
    assert torch.load(checkpoint, weights_only=False)["epoch"] == 1
    resumed, _ = jointnet_training.train_jointnet(*data, 3, 3e-3, 0, shape, checkpoint)
    for name, value in whole.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[name], value, rtol=0, atol=0)


def _loss(net, windows, joints, located):
    torch.manual_seed(5)
    views, pts, mask = augment(windows, joints, located)
    mask[:, :13] = False  # the head top alone has a cue
    with torch.no_grad():
        return float(jointnet_loss(net(views), pts, mask))


def test_a_training_from_a_network_goes_on_from_its_weights():
    """init (`ds3d train-jointnet --from-current`): the training starts from the given state,
    float16 as a model stores it, not from a fresh network; at a vanishing learning rate the
    convolutions stay where they were."""
    data, shape = _six_windows(5)
    first, _ = jointnet_training.train_jointnet(*data, 2, 3e-3, 0, shape)
    stored = {k: v.half() if v.is_floating_point() else v for k, v in first.state_dict().items()}
    later, _ = jointnet_training.train_jointnet(*data, 1, 1e-9, 1, shape, init=stored)
    fresh, _ = jointnet_training.train_jointnet(*data, 1, 1e-9, 1, shape)
    weight = "head.weight"
    start = stored[weight].float()
    torch.testing.assert_close(later.state_dict()[weight], start, rtol=0, atol=1e-3)
    assert (fresh.state_dict()[weight] - start).abs().max() > 1e-2
