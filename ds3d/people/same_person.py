"""When two poses answered in one image are one person found twice: the same-person rules of
ds3d.people.finder's answer, beside the boxes' overlap (ds3d.boxes.suppress)."""

from __future__ import annotations

import numpy as np

from ds3d.boxes import person_boxes
from ds3d.skeleton import LIMBS


def _extents(poses: np.ndarray) -> np.ndarray:
    """poses (N, 14, 2) px -> (N, N): the longer side of the larger of each pair's boxes."""
    boxes = person_boxes(poses)
    extent = (boxes[:, 2:] - boxes[:, :2]).max(-1)  # (N,)
    return np.maximum(extent[:, None], extent[None, :])


def shared_joints(poses: np.ndarray, radius: float) -> np.ndarray:
    """poses (N, 14, 2) px -> (N, N) int: for each pair, how many of their joints lie within
    `radius` times the longer side of the larger of their two boxes of each other. Two answers
    that share several joints are one person found twice (a whole pose and a partial one);
    two people side by side, even with overlapping boxes, share none."""
    poses = np.asarray(poses, np.float64)
    distance = np.linalg.norm(poses[:, None] - poses[None], axis=-1)  # (N, N, 14)
    return (distance < radius * _extents(poses)[..., None]).sum(-1)


def joints_on_bones(poses: np.ndarray, radius: float) -> np.ndarray:
    """poses (N, 14, 2) px -> (N, N) int: [i, j] how many of pose i's joints lie within `radius`
    times the longer side of the larger of the two boxes of pose j's bones (the segments of
    ds3d.skeleton.LIMBS). A second reading of one body draws its joints along the first's
    limbs, at other places than the first's joints (a leg read as a whole person, a pose
    turned end to end); a person beside another keeps most of their joints off its bones."""
    poses = np.asarray(poses, np.float64)
    child, parent = (np.array(side) for side in zip(*LIMBS, strict=True))
    start, along = poses[:, parent], poses[:, child] - poses[:, parent]  # (N, 13, 2) each
    offset = poses[:, None, :, None] - start[None, :, None]  # (N_i, N_j, 14, 13, 2)
    length = np.maximum((along**2).sum(-1), 1e-12)[None, :, None]  # (1, N_j, 1, 13)
    t = np.clip((offset * along[None, :, None]).sum(-1) / length, 0.0, 1.0)
    gap = np.linalg.norm(offset - t[..., None] * along[None, :, None], axis=-1).min(-1)
    return (gap < radius * _extents(poses)[..., None]).sum(-1)
