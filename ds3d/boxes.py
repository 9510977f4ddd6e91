"""Person boxes (x0, y0, x1, y1) px: from joints, their overlap, and non-maximum suppression.

One definition serves the search for people (ds3d.image2d.search), the pipeline's answer and
the people protocol's scores (ds3d.evaluation.people), so that a box means the same everywhere.
"""

from __future__ import annotations

import numpy as np

from ds3d.errors import InvalidBox
from ds3d.skeleton import LIMBS

BOX_MARGIN = 0.1  # of the joints' extent, on every side


def checked_box(box, width: int, height: int) -> np.ndarray:
    """A person box given by a user, (x0, y0, x1, y1) px, checked against its image of width x
    height px -> (4,) float32. The one place where the CLI, the Python API and the service
    refuse a box: raises InvalidBox, naming why, when it is not four finite numbers, its corners
    are reversed or it has no area, or it does not overlap the image. A box that overlaps the
    image only in part is kept (the 2D stage crops what lies inside)."""
    try:
        values = np.asarray(box, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise InvalidBox(f"bbox must be four numbers x0, y0, x1, y1; got {box!r}") from err
    if values.size != 4:
        raise InvalidBox(f"bbox must be four numbers x0, y0, x1, y1; got {values.size}")
    if not np.isfinite(values).all():
        raise InvalidBox("bbox has a NaN or infinite coordinate")
    x0, y0, x1, y1 = values
    if x1 <= x0 or y1 <= y0:
        raise InvalidBox(
            f"bbox [{x0:g}, {y0:g}, {x1:g}, {y1:g}] has no area: it wants x1 > x0 and y1 > y0 "
            "(corners x0, y0, x1, y1, not x, y, width, height)"
        )
    if x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        raise InvalidBox(
            f"bbox [{x0:g}, {y0:g}, {x1:g}, {y1:g}] lies outside the {width}x{height} image"
        )
    return values.astype(np.float32)


def person_boxes(joints: np.ndarray, located: np.ndarray | None = None) -> np.ndarray:
    """(P, 14, 2) px (and (P, 14) bool, the joints to use) -> (P, 4) x0, y0, x1, y1 px: the
    joints' bounding box widened by BOX_MARGIN of its extent on every side."""
    joints = np.asarray(joints, dtype=np.float64)
    mask = np.ones(joints.shape[:2], bool) if located is None else np.asarray(located, bool)
    low = np.where(mask[..., None], joints, np.inf).min(1)
    high = np.where(mask[..., None], joints, -np.inf).max(1)
    pad = BOX_MARGIN * (high - low)
    return np.concatenate([low - pad, high + pad], 1)


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union of boxes a (N, 4) and b (M, 4) -> (N, M)."""
    a, b = np.asarray(a, np.float64).reshape(-1, 4), np.asarray(b, np.float64).reshape(-1, 4)
    top_left = np.maximum(a[:, None, :2], b[None, :, :2])
    bottom_right = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(bottom_right - top_left, 0, None).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).prod(-1)
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def suppress(
    boxes: np.ndarray,
    scores: np.ndarray,
    overlap: float = 0.5,
    same: np.ndarray | None = None,
) -> np.ndarray:
    """Greedy non-maximum suppression: boxes (N, 4), scores (N,) higher = surer -> the indices
    kept, best first: each box kept unless it overlaps a better kept one by IoU > overlap, or
    `same` (N, N) bool, where given, says the two are one."""
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    duplicate = iou(boxes, boxes) > overlap
    if same is not None:
        duplicate |= same
    kept: list[int] = []
    for i in order:
        if not any(duplicate[i, k] for k in kept):
            kept.append(int(i))
    return np.array(kept, dtype=np.int64)


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
