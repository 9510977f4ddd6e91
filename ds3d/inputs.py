"""Validation of user-supplied poses and cameras at the library's edge: shapes, dtypes, finite
values within MAX_COORDINATE_PX. Everything past this point may assume well-formed tensors."""

from __future__ import annotations

import numpy as np
import torch

from ds3d.errors import InvalidPose
from ds3d.skeleton import NUM_JOINTS

# The largest magnitude of a 2D coordinate or a camera matrix entry, px: far beyond any image
# (a 40-megapixel photo's side is below 1e5), and small enough that the fits' squared
# residuals stay finite in float32 (1e30 px squared overflows it, and the energy became NaN).
MAX_COORDINATE_PX = 1e7
# The shortest focal length taken, px: below it a camera would see more than a half-space of a
# few-pixel image; in float32 a tinier positive one may round to zero.
MIN_FOCAL_PX = 1.0


def _tensor(value, name: str) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value.detach().float()
    try:
        return torch.as_tensor(np.asarray(value, dtype=np.float32))
    except (TypeError, ValueError) as err:
        raise InvalidPose(f"{name}: not a numeric array ({err})") from err


def joints_2d_batch(joints_2d) -> torch.Tensor:
    """(B, 14, 2) or (14, 2) array-like, px -> (B, 14, 2) float32 tensor; raises InvalidPose."""
    x = _tensor(joints_2d, "joints_2d")
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[-1] != 2:
        raise InvalidPose(f"joints_2d: expected shape (B, 14, 2), got {tuple(x.shape)}")
    if x.shape[1] != NUM_JOINTS:
        raise InvalidPose(f"joints_2d: expected {NUM_JOINTS} joints (LSP order), got {x.shape[1]}")
    if not bool(torch.isfinite(x).all()):
        raise InvalidPose("joints_2d: contains NaN or infinite coordinates")
    if bool((x.abs() > MAX_COORDINATE_PX).any()):
        raise InvalidPose(f"joints_2d: coordinates beyond +-{MAX_COORDINATE_PX:g} px")
    return x


def visibility_batch(visible, batch: int) -> torch.Tensor:
    """None or (B, 14) / (14,) bool-like -> (B, 14) bool; at least 2 visible joints per pose."""
    if visible is None:
        return torch.ones(batch, NUM_JOINTS, dtype=torch.bool)
    v = torch.as_tensor(np.asarray(visible)).bool()
    if v.ndim == 1:
        v = v[None].expand(batch, -1)
    if tuple(v.shape) != (batch, NUM_JOINTS):
        raise InvalidPose(f"visible: expected shape ({batch}, 14), got {tuple(v.shape)}")
    if bool((v.sum(-1) < 2).any()):
        raise InvalidPose("visible: every pose needs at least two visible joints")
    return v


def focal_length(focal_px) -> float:
    """A focal length in px, checked: finite, at least MIN_FOCAL_PX, within MAX_COORDINATE_PX."""
    value = float(focal_px)
    if not MIN_FOCAL_PX <= value <= MAX_COORDINATE_PX:  # NaN fails too
        raise InvalidPose(
            f"focal_px: need a focal length of {MIN_FOCAL_PX:g} to {MAX_COORDINATE_PX:g} px, "
            f"got {focal_px}"
        )
    return value


def intrinsics_batch(intrinsics, batch: int) -> torch.Tensor | None:
    """None or (B, 3, 3) / (3, 3) pinhole matrices -> (B, 3, 3) float32 with focal lengths of
    at least MIN_FOCAL_PX."""
    if intrinsics is None:
        return None
    k = _tensor(intrinsics, "intrinsics")
    if k.ndim == 2:
        k = k[None].expand(batch, -1, -1)
    if tuple(k.shape) != (batch, 3, 3):
        raise InvalidPose(f"intrinsics: expected shape ({batch}, 3, 3), got {tuple(k.shape)}")
    focal = torch.stack((k[:, 0, 0], k[:, 1, 1]), -1)
    if not bool(torch.isfinite(k).all()) or bool((focal < MIN_FOCAL_PX).any()):
        raise InvalidPose(
            f"intrinsics: need finite values and focal lengths of at least {MIN_FOCAL_PX:g} px"
        )
    if bool((k.abs() > MAX_COORDINATE_PX).any()):
        raise InvalidPose(f"intrinsics: entries beyond +-{MAX_COORDINATE_PX:g} px")
    return k
