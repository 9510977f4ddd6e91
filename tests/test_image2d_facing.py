"""The facing descriptor: aligned to the pose, blind to its left/right labels, read by a Forest."""

import numpy as np
import torch

from ds3d.image2d import facing
from ds3d.image2d.features import evaluate_pool, pad_channels
from ds3d.image2d.train import observer_centric
from ds3d.skeleton import FLIP, NUM_JOINTS


def _poses(n: int, seed: int) -> torch.Tensor:
    """Random (n, 14, 2) poses in a 60 x 80 px image, away from its border."""
    return torch.from_numpy(np.random.default_rng(seed).uniform(15, 45, (n, NUM_JOINTS, 2)))


def test_observer_centric_matches_the_training_relabelling():
    poses = _poses(50, 0).float()
    want = np.stack([observer_centric(p, np.ones(NUM_JOINTS, bool))[0] for p in poses.numpy()])
    np.testing.assert_array_equal(facing.observer_centric(poses).numpy(), want)


def test_descriptor_samples_the_channels_at_the_pose_points_whatever_the_labels():
    # Channel 0 is the x coordinate, channel 1 the y coordinate: a 3 x 3 box mean keeps a ramp,
    # so away from the border the descriptor reads back its own sampling points.
    h, w = 60, 80
    yy, xx = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    channels = torch.zeros(1, 12, h, w)
    channels[0, 0], channels[0, 1] = xx, yy
    poses = _poses(4, 1).float()
    desc = facing.descriptor(channels.expand(4, -1, -1, -1), poses)
    assert desc.shape == (4, 12, 1, facing.NUM_POINTS)
    points = facing.sample_points(facing.observer_centric(poses))
    inside = ((points > 2) & (points < torch.tensor([w - 3.0, h - 3.0]))).all(-1)
    torch.testing.assert_close(desc[:, 0, 0][inside], points[..., 0][inside])
    torch.testing.assert_close(desc[:, 1, 0][inside], points[..., 1][inside])
    # the head grid is centred between the neck and the head top
    centre = points[:, : facing.HEAD_GRID**2].mean(1)
    torch.testing.assert_close(centre, (poses[:, 12] + poses[:, 13]) / 2)
    # swapping every left/right label leaves the descriptor as it was
    torch.testing.assert_close(facing.descriptor(channels, poses[:1, list(FLIP)]), desc[:1])


def test_the_pool_reads_the_descriptor_as_a_one_row_image():
    desc = torch.rand(1, 12, 1, facing.NUM_POINTS)
    padded = pad_channels(desc, facing.NUM_POINTS)[0]
    origin = torch.zeros(1, 2, dtype=torch.long)
    values = evaluate_pool(padded, facing.NUM_POINTS, origin, facing.descriptor_pool())
    torch.testing.assert_close(values[0], desc[0, :, 0].reshape(-1))
