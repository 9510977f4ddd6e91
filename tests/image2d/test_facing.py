"""The facing model (ds3d.image2d.facing): a window around the torso, blind to left and right."""

from __future__ import annotations

import numpy as np
import torch

from ds3d.image2d import facing
from ds3d.skeleton import FLIP, NUM_JOINTS


def _poses(n: int, seed: int) -> torch.Tensor:
    """Random (n, 14, 2) poses in a 60 x 80 px image, away from its border."""
    return torch.from_numpy(np.random.default_rng(seed).uniform(15, 45, (n, NUM_JOINTS, 2)))


def _ramps(h: int, w: int) -> torch.Tensor:
    """(1, 3, h, w): channel 0 = x, channel 1 = y, channel 2 = 1."""
    yy, xx = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    return torch.stack([xx, yy, torch.ones(h, w)])[None]


def test_the_window_centre_ignores_left_and_right_labels():
    poses = _poses(8, 1).float()
    centre = facing.crop_centre(poses)
    torch.testing.assert_close(facing.crop_centre(poses[:, list(FLIP)]), centre)
    hips = (poses[:, 2] + poses[:, 3]) / 2
    torch.testing.assert_close(centre, poses[:, 12] + (hips - poses[:, 12]) / 4)


def test_crop_reads_the_window_pixels_scaled_mirrored_and_zero_outside():
    lab = _ramps(200, 300)
    centre = torch.tensor([[150.0, 100.0], [10.0, 20.0]])
    out = facing.crop(lab.expand(2, -1, -1, -1), centre, torch.tensor([1.0, 0.5]))
    assert out.shape == (2, 3, facing.CROP, facing.CROP)
    k = torch.arange(facing.CROP) - (facing.CROP - 1) / 2
    torch.testing.assert_close(out[0, 0, 5], 150 + k)  # x along a row
    torch.testing.assert_close(out[0, 1, :, 7], 100 + k)  # y down a column
    x = 10 + 0.5 * k  # zoom: half a pixel per step, from x = -5.75
    inside = x >= 0
    torch.testing.assert_close(out[1, 0, 40][inside], x[inside])
    assert (out[1, 2, 40][~inside] < 1).all() and (out[1, 2, 40][inside] == 1).all()
    mirrored = facing.crop(lab, centre[:1], flip=torch.tensor([True]))
    torch.testing.assert_close(mirrored, out[:1].flip(-1))


def test_probability_of_an_image_does_not_depend_on_its_batch():
    net = facing.FacingNet().eval()
    rng = np.random.default_rng(2)
    images = [torch.from_numpy(rng.uniform(0, 1, (3, h, w)).astype(np.float32)) for h, w in
              ((70, 50), (60, 90))]  # fmt: skip
    batch = torch.zeros(2, 3, 70, 90)
    for i, im in enumerate(images):
        batch[i, :, : im.shape[1], : im.shape[2]] = im
    poses = _poses(2, 3).float()
    sizes = [tuple(im.shape[1:]) for im in images]
    together = facing.faces_camera_probability(net, batch, poses, sizes)
    for i, im in enumerate(images):
        alone = facing.faces_camera_probability(net, im[None], poses[i : i + 1], [sizes[i]])
        torch.testing.assert_close(together[i : i + 1], alone, rtol=0, atol=0)
    assert ((together > 0) & (together < 1)).all()


def test_probability_is_mirror_invariant():
    net = facing.FacingNet().eval()
    lab = torch.from_numpy(np.random.default_rng(4).uniform(0, 1, (1, 3, 60, 80)).astype("f4"))
    poses = _poses(1, 5).float()
    mirrored = poses[:, list(FLIP)].clone()
    mirrored[..., 0] = 79 - mirrored[..., 0]
    p = facing.faces_camera_probability(net, lab, poses, [(60, 80)])
    q = facing.faces_camera_probability(net, lab.flip(-1), mirrored, [(60, 80)])
    torch.testing.assert_close(p, q)
