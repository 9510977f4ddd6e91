"""The 2D stage's per-pixel features (ds3d.image2d.features)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ds3d.image2d.features import box_mean, image_channels, rgb_to_lab


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
