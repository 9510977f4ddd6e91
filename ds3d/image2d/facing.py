"""Does the person face the camera? A descriptor aligned to the 2D pose, read by a small forest.

The cascade cannot tell left from right when a person turns their back: it labels the limb on
the image's left "right" in nearly every image (docs/RESULTS.md). What tells is mostly the head
(a face or the back of a head) and the torso. The descriptor samples the 12 image channels,
box-blurred, on a 6 x 6 grid over the head (a square on the neck -> head-top axis, 1.2 half
head lengths from its centre) and a 4 x 4 grid spanning the shoulders and hips: 52 points.

The pose it is aligned to is made observer-centric first (observer_centric):
the arm whose shoulder is on the image's left is "right", as the cascade's answers effectively
are. So the descriptor never sees the left/right labels it has to judge.

To reuse the forest machinery (ds3d.image2d.forest), the descriptor is laid out as a 12-channel
image of 1 x 52 pixels, read at pixel (0, 0) with offsets (0, k): a tree's split on point k of
channel c is the pixel comparison (c, (0, k), use2 = 0).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ds3d.image2d.features import NUM_IMAGE_CHANNELS, ComparisonPool, box_mean
from ds3d.skeleton import HEAD_TOP, L_HIP, L_SHOULDER, NECK, R_HIP, R_SHOULDER

HEAD_GRID = 6
TORSO_GRID = 4
NUM_POINTS = HEAD_GRID**2 + TORSO_GRID**2
# (right chain, left chain) of the arms from the shoulder and of the legs from the hip.
CHAINS = (((8, 7, 6), (9, 10, 11)), ((2, 1, 0), (3, 4, 5)))


def observer_order(joints: torch.Tensor) -> torch.Tensor:
    """(B, 14, 2) poses (x, y) -> (B, 14) long: the joint order that relabels each arm (leg)
    pair so that the one whose shoulder (hip) has the smaller x is the right one."""
    order = torch.arange(joints.shape[-2]).repeat(len(joints), 1)
    for right, left in CHAINS:
        swap = joints[:, right[0], 0] > joints[:, left[0], 0]  # (B,)
        for r, k in zip(right, left, strict=True):
            order[swap, r], order[swap, k] = k, r
    return order


def observer_centric(joints: torch.Tensor) -> torch.Tensor:
    """(B, 14, 2) poses -> the same relabelled by observer_order."""
    order = observer_order(joints)
    return torch.gather(joints, 1, order[..., None].expand_as(joints))


def sample_points(joints: torch.Tensor) -> torch.Tensor:
    """(B, 14, 2) observer-centric poses (x, y) px -> (B, 52, 2) descriptor points (x, y) px."""
    t = torch.linspace(-1.0, 1.0, HEAD_GRID)
    a, b = torch.meshgrid(t, t, indexing="ij")
    half = (joints[:, HEAD_TOP] - joints[:, NECK]) / 2  # (B, 2) along the head
    across = torch.stack([-half[:, 1], half[:, 0]], -1)
    centre = joints[:, NECK] + half
    head = centre[:, None] + 1.2 * (
        a.reshape(1, -1, 1) * across[:, None] + b.reshape(1, -1, 1) * half[:, None]
    )
    t = torch.linspace(0.0, 1.0, TORSO_GRID)
    a, b = torch.meshgrid(t, t, indexing="ij")
    a, b = a.reshape(1, -1, 1), b.reshape(1, -1, 1)
    shoulder, hip = joints[:, None, R_SHOULDER], joints[:, None, R_HIP]
    top = shoulder + a * (joints[:, None, L_SHOULDER] - shoulder)
    bottom = hip + a * (joints[:, None, L_HIP] - hip)
    return torch.cat([head, top + b * (bottom - top)], dim=1)


def descriptor(channels: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
    """channels: (B, 12, H, W) from image_channels; joints: (B, 14, 2) (x, y) px on them, any
    labelling -> (B, 12, 1, 52) float32, the channels (3 x 3 box mean) at the points of the
    observer-centric pose, bilinear, 0 outside the image."""
    h, w = channels.shape[-2:]
    points = sample_points(observer_centric(joints.float()))
    grid = torch.stack([points[..., 0] / max(w - 1, 1), points[..., 1] / max(h - 1, 1)], -1) * 2 - 1
    return F.grid_sample(box_mean(channels, 1), grid[:, None], mode="bilinear", align_corners=True)


def descriptor_pool() -> ComparisonPool:
    """Every (channel, point) of the descriptor as a pixel comparison from pixel (0, 0)."""
    channel, point = np.meshgrid(
        np.arange(NUM_IMAGE_CHANNELS), np.arange(NUM_POINTS), indexing="ij"
    )
    n = channel.size
    offset1 = np.stack([np.zeros(n, dtype=np.int64), point.reshape(-1)], 1)
    return ComparisonPool(
        channel.reshape(-1).astype(np.int64),
        offset1,
        np.zeros((n, 2), dtype=np.int64),
        np.zeros(n, dtype=np.float32),
    )
