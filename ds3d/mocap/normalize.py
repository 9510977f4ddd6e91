"""Pose normalisation, for the database and for queries.

3D (the paper's normalised pose space): the pose is moved so that the hip midpoint is the origin
and turned about the vertical axis so that it faces a fixed direction. The result lives in the
*body frame*, a camera-style frame: x = the person's left, y = down, z = x cross y, so that the
person faces -z, i.e. looks at a virtual camera at azimuth 0 that views along +z.

2D (the paper's normalised 2D space): translate and scale so that the joints' y coordinates span
[-1, 1]; x is centred on the middle of its extent and scaled by the same factor.
"""

from __future__ import annotations

import torch

from ds3d.skeleton import L_HIP, L_SHOULDER, R_HIP, R_SHOULDER, hip_midpoint


def normalize_3d(poses: torch.Tensor, up: tuple[float, float, float] = (0, 0, 1)) -> torch.Tensor:
    """World poses -> body frame.

    poses: (..., 14, 3) float, mm, in a world frame whose vertical axis is `up` (Human3.6M and our
    CMU reader: z up). Returns (..., 14, 3), mm, root at the hip midpoint, facing -z.
    The facing direction comes from the hip and shoulder lines together, which is steadier than
    the hips alone when the pelvis twists.
    """
    up_axis = poses.new_tensor(up)
    up_axis = up_axis / up_axis.norm()
    centred = poses - hip_midpoint(poses)[..., None, :]
    left = (centred[..., L_HIP, :] - centred[..., R_HIP, :]) + (
        centred[..., L_SHOULDER, :] - centred[..., R_SHOULDER, :]
    )
    left = left - (left @ up_axis)[..., None] * up_axis  # horizontal part only
    left = left / left.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    down = -up_axis.expand_as(left)
    back = torch.linalg.cross(left, down)
    frame = torch.stack([left, down, back], dim=-2)  # (..., 3, 3): rows are the body axes
    return centred @ frame.transpose(-1, -2)


def normalize_2d(points: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Translate and scale 2D poses so that y spans [-1, 1].

    points: (..., J, 2) float, any unit. mask: optional (J,) or (..., J) bool, the joints that
    take part (the others are ignored for the extent and set to 0 in the output).
    Returns (..., J, 2), unitless. The half-span is floored at a quarter of the x extent so that a
    lying person (tiny y extent) does not blow up to huge x values.
    """
    if mask is None:
        mask = torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
    mask = mask.expand(points.shape[:-1])[..., None]
    big = torch.finfo(points.dtype).max
    lo = torch.where(mask, points, big).amin(dim=-2, keepdim=True)
    hi = torch.where(mask, points, -big).amax(dim=-2, keepdim=True)
    centre = (lo + hi) / 2
    extent = hi - lo
    half_span = torch.maximum(extent[..., 1:2], extent[..., 0:1] / 2).clamp_min(1e-6) / 2
    return torch.where(mask, (points - centre) / half_span, 0.0)
