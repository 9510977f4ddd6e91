"""The joint network (ds3d.image2d.jointnet): its grid mapping and output."""

from __future__ import annotations

import copy

import torch
from torch import nn

from ds3d.image2d.jointnet import (
    MARGIN,
    STRIDE,
    JointNet,
    JointNetShape,
    ScaledLogits,
    fold_batch_norms,
    logits_on_grid,
    padded_logits,
    padded_logits_each,
    read_logits,
    spatial_softmax,
)
from ds3d.skeleton import NUM_JOINTS


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


def test_a_crops_maps_are_read_off_a_view_of_the_image_at_its_own_pixels():
    v, u = torch.meshgrid(torch.arange(60.0), torch.arange(50.0), indexing="ij")
    view = ScaledLogits((u + 100 * v).expand(1, NUM_JOINTS, 60, 50), (0.8, 0.75))
    # A crop whose corner is at image px (20, 12), resized by (0.9, 0.85): 40 x 30 px.
    out = read_logits([view], (0.9, 0.85), (20, 12), 40, 30)
    assert out is not None and out.shape == (1, NUM_JOINTS, (40 + 2 * MARGIN) // 4, 16)
    i, j = torch.meshgrid(torch.arange(18.0), torch.arange(16.0), indexing="ij")
    cells = []
    for cell, scale, corner, level in ((j, 0.9, 20, 0.8), (i, 0.85, 12, 0.75)):
        crop_px = STRIDE * cell - MARGIN  # the padded input's px of the output cell
        image_px = (crop_px + 0.5) / scale - 0.5 + corner
        level_px = (image_px + 0.5) * level - 0.5
        cells.append((level_px + MARGIN) / STRIDE)  # the view's output cell there
    # The view's values are linear in its cells: reading them bilinearly is exact.
    torch.testing.assert_close(out[0, 3], cells[0] + 100 * cells[1])
    # A view more than the network's zoom away (0.8 / 0.5) is not read.
    assert read_logits([view], (0.5, 0.5), (20, 12), 40, 30) is None


def test_spatial_softmax_is_a_distribution_over_the_cells():
    logits = torch.randn(2, NUM_JOINTS, 5, 6)
    probs = spatial_softmax(logits)
    torch.testing.assert_close(probs.sum((2, 3)), torch.ones(2, NUM_JOINTS))
    assert probs[0, 3].argmax() == logits[0, 3].argmax()


def test_network_output_is_a_quarter_of_the_input_rounded_up():
    net = JointNet().eval()
    with torch.no_grad():
        assert net(torch.zeros(1, 3, 50, 37)).shape == (1, NUM_JOINTS, 13, 10)


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


def test_folding_the_batch_norms_keeps_the_network():
    torch.manual_seed(0)
    net = JointNet(JointNetShape((8, 8, 8), (1, 1, 1)))
    for m in net.modules():  # batch norms that do something
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.normal_()
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.normal_()
            m.bias.data.normal_()
    net.eval()
    lab = torch.randn(2, 3, 40, 28)
    with torch.no_grad():
        expected = net(lab)
        folded = fold_batch_norms(copy.deepcopy(net))
        assert not any(isinstance(m, nn.BatchNorm2d) for m in folded.modules())
        torch.testing.assert_close(folded(lab), expected, rtol=1e-4, atol=1e-4)


def test_images_batched_by_padded_shape_get_the_maps_they_get_alone():
    torch.manual_seed(0)
    net = fold_batch_norms(JointNet(JointNetShape((8, 8, 8), (1, 1, 1))))
    # 70 x 50 and 66 x 52 share a padded shape (one call), 30 x 90 has its own.
    labs = [torch.randn(1, 3, h, w) for h, w in ((70, 50), (30, 90), (66, 52), (70, 50))]
    each = padded_logits_each(net, labs)
    for lab, maps in zip(labs, each, strict=True):
        torch.testing.assert_close(maps, padded_logits(net, lab), rtol=1e-4, atol=1e-4)
