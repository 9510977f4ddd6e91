"""Fast pictures of results with OpenCV, for every image of a run and every frame of a video: the
2D skeletons drawn over the image, and the 3D skeletons on a panel beside it.

Colours as ds3d.viz.render (the person's right red, left blue, neck and head green); a joint's dot
is as bright as the 2D stage is sure of it. Arrays are RGB throughout.
"""

from __future__ import annotations

import cv2
import numpy as np

from ds3d.skeleton import JOINT_SIDES, LIMBS, NUM_JOINTS

RIGHT, LEFT, CENTRE = (214, 39, 40), (31, 119, 180), (44, 160, 44)  # matplotlib's tab colours
SIDE_COLOURS = {"right": RIGHT, "left": LEFT, "centre": CENTRE}  # by ds3d.skeleton.JOINT_SIDES
PANEL_BACKGROUND = (250, 250, 250)
# The 3D panel shows a fixed 2.4 m square per person, so that a video's skeleton keeps its size.
PANEL_SPAN_MM = 2400.0


def limb_colour(child: int) -> tuple[int, int, int]:
    """RGB of the limb ending at joint `child`: the person's right red, left blue, neck and
    head green (ds3d.viz.render's and the web page's too)."""
    return SIDE_COLOURS[JOINT_SIDES[child]]


def draw_limbs(canvas: np.ndarray, points: np.ndarray, thickness: int) -> None:
    """One skeleton's limbs onto canvas (H, W, 3) uint8, in place: points (14, 2) int px."""
    for child, parent in LIMBS:
        start, end = tuple(points[child]), tuple(points[parent])
        cv2.line(canvas, start, end, limb_colour(child), thickness, cv2.LINE_AA)


def draw_2d(image: np.ndarray, joints_2d: np.ndarray, confidence: np.ndarray | None = None):
    """image (H, W, 3) uint8 RGB; joints_2d (P, 14, 2) px, one skeleton per person; confidence
    (P, 14) in [0, 1] or None. Returns a drawn copy of the image."""
    out = np.ascontiguousarray(image).copy()
    people = np.asarray(joints_2d, np.float64).reshape(-1, NUM_JOINTS, 2)
    sure = np.ones(people.shape[:2]) if confidence is None else np.asarray(confidence)
    thickness = max(1, round(max(out.shape[:2]) / 250))
    for person, person_sure in zip(people, sure.reshape(people.shape[:2]), strict=True):
        points = np.round(person).astype(np.int32)
        draw_limbs(out, points, thickness)
        for point, p in zip(points, person_sure, strict=True):
            shade = int(255 * float(np.clip(p, 0, 1)))
            cv2.circle(out, tuple(point), thickness + 1, (shade, shade, shade), -1, cv2.LINE_AA)
            cv2.circle(out, tuple(point), thickness + 1, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def draw_3d(joints_3d: np.ndarray, height: int, width: int, azimuth: float = 35.0) -> np.ndarray:
    """joints_3d (P, 14, 3) mm, camera-oriented (x right, y down, z away), root-centred; the
    people side by side a metre apart, seen from `azimuth` degrees around the vertical (0: the
    camera's view), orthographic, with the ground under the lowest foot. Returns (height,
    width, 3) uint8 RGB."""
    panel = np.full((height, width, 3), PANEL_BACKGROUND, np.uint8)
    people = np.asarray(joints_3d, np.float64).reshape(-1, NUM_JOINTS, 3)
    if not len(people):
        return panel
    people = people + np.arange(len(people))[:, None, None] * np.array([1000.0, 0.0, 0.0])
    people -= people.reshape(-1, 3).mean(0) * np.array([1.0, 0.0, 1.0])  # centre the group
    turn = np.radians(azimuth)
    across = people[..., 0] * np.cos(turn) + people[..., 2] * np.sin(turn)  # mm, to the right
    down = people[..., 1]
    span = PANEL_SPAN_MM + 1000.0 * (len(people) - 1)
    px_per_mm = min(height / PANEL_SPAN_MM, width / span)
    centre = np.array([width / 2, height / 2])
    points = np.stack([across, down], -1) * px_per_mm + centre
    floor = round(float(down.max() * px_per_mm + centre[1]))
    cv2.line(panel, (0, floor), (width - 1, floor), (190, 190, 190), 1, cv2.LINE_AA)
    thickness = max(1, round(min(height, width) / 200))
    for person in np.round(points).astype(np.int32):
        draw_limbs(panel, person, thickness)
    return panel


def plot(
    image: np.ndarray,
    joints_2d: np.ndarray,
    joints_3d: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
) -> np.ndarray:
    """The image with its 2D skeletons and, with joints_3d (P, 14, 3) mm, the 3D panel beside it
    (as tall as the image, three quarters as wide). (H, W [+ 3H/4], 3) uint8 RGB."""
    drawn = draw_2d(image, joints_2d, confidence)
    if joints_3d is None:
        return drawn
    height = drawn.shape[0]
    panel = draw_3d(joints_3d, height, max(2, round(0.75 * height) // 2 * 2))
    return np.concatenate([drawn, panel], 1)
