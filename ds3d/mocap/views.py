"""The paper's virtual cameras: orthographic views of body-frame poses.

A view is a rotation R(azimuth, elevation) = R_x(elevation) @ R_y(azimuth) that takes a body-frame
pose (x left-of-person, y down, z back; see ds3d.mocap.normalize) into a camera-oriented frame
(x right, y down, z away from the camera); the orthographic projection keeps (x, y). Azimuth turns
the camera around the person; positive elevation lifts the camera above the person, looking down.
"""

from __future__ import annotations

import math

import torch

AZIMUTHS_DEG: tuple[float, ...] = tuple(range(0, 360, 15))  # 24 azimuths, 0..345
ELEVATIONS_DEG: tuple[float, ...] = tuple(range(0, 90, 15))  # 6 elevations, 0..75


def view_rotations(
    azimuths_deg: tuple[float, ...] = AZIMUTHS_DEG,
    elevations_deg: tuple[float, ...] = ELEVATIONS_DEG,
) -> torch.Tensor:
    """(V, 3, 3) float32 rotations, V = len(azimuths) * len(elevations) (144 by default),
    ordered elevation-major: view v = e * len(azimuths) + a."""
    az = torch.tensor(azimuths_deg, dtype=torch.float64) * math.pi / 180
    el = torch.tensor(elevations_deg, dtype=torch.float64) * math.pi / 180
    ca, sa, ce, se = az.cos(), az.sin(), el.cos(), el.sin()
    one, zero = torch.ones_like(az), torch.zeros_like(az)
    rot_y = torch.stack(
        [
            torch.stack([ca, zero, sa], -1),
            torch.stack([zero, one, zero], -1),
            torch.stack([-sa, zero, ca], -1),
        ],
        -2,
    )
    one, zero = torch.ones_like(el), torch.zeros_like(el)
    rot_x = torch.stack(
        [
            torch.stack([one, zero, zero], -1),
            torch.stack([zero, ce, -se], -1),
            torch.stack([zero, se, ce], -1),
        ],
        -2,
    )
    return (rot_x[:, None] @ rot_y[None]).reshape(-1, 3, 3).float()


def rotate(poses: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """Apply rotations to poses. poses: (..., J, 3); rotations: (..., 3, 3) -> (..., J, 3)."""
    # column by column: far faster than as many tiny (J, 3) @ (3, 3) products, and no larger
    # intermediate than the result (the index build rotates a million poses at once)
    r = rotations[..., None, :, :]  # (..., 1, 3, 3)
    return poses[..., 0:1] * r[..., 0] + poses[..., 1:2] * r[..., 1] + poses[..., 2:3] * r[..., 2]
