"""Person boxes (x0, y0, x1, y1) px: from joints, their overlap, and non-maximum suppression.

One definition serves the search for people (ds3d.people), the pipeline's answer and the people
protocol's scores (ds3d.evaluation.people), so that a box means the same everywhere.
"""

from __future__ import annotations

import numpy as np

BOX_MARGIN = 0.1  # of the joints' extent, on every side


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
