"""Training of the facing CNN (ds3d.training.facing)."""

from __future__ import annotations

import torch

from ds3d.image2d import facing
from ds3d.training.config import TrainConfig
from ds3d.training.facing import FACING_MARGIN, train_facing


def test_training_learns_a_mirror_invariant_cue():
    # Faces the camera: the upper half of the window is bright; away: the lower half. A
    # mirror keeps the cue, as it keeps whether a person faces the camera.
    n = 96
    labels = (torch.arange(n) % 2).float()
    noise = torch.Generator().manual_seed(0)
    windows = torch.rand(n, 3, FACING_MARGIN, FACING_MARGIN, generator=noise) * 0.2
    half = FACING_MARGIN // 2
    windows[labels == 1, :, :half] += 0.6
    windows[labels == 0, :, half:] += 0.6
    net = train_facing(windows.half(), labels, TrainConfig(facing_epochs=8, facing_lr=1e-2))
    centre = torch.full((n, 2), (FACING_MARGIN - 1) / 2)
    with torch.no_grad():
        p = torch.sigmoid(net(facing.crop(windows, centre)))
    # Ranked apart (a handful of steps leave batch norm's running statistics uncalibrated).
    assert p[labels == 1].min() > p[labels == 0].max()
