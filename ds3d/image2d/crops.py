"""Where each image's working region comes from: the person box (with a margin) or the whole
image, and the base scale that brings a person filling it to the canonical extent."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ds3d.image2d.jointnet import ScaledLogits
from ds3d.image2d.params import EstimatorParams


def resize_image(image: np.ndarray, scale: float) -> np.ndarray:
    """(H, W, 3) uint8 -> (round(H * scale), round(W * scale), 3) uint8, area-averaged when
    shrinking. The exact per-axis factors are the ratios of the shapes."""
    h, w = image.shape[:2]
    nh, nw = max(round(h * scale), 1), max(round(w * scale), 1)
    if (nh, nw) == (h, w):
        return image
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(image, (nw, nh), interpolation=interp)


@dataclass
class Crop:
    """Where one image's working region comes from: its top-left corner (x0, y0) in image px
    and the base scale (working px per image px); views: the joint network's maps of the whole
    image at some scales where the search computed them (jointnet.read_logits)."""

    image: np.ndarray
    x0: int
    y0: int
    base: float
    views: Sequence[ScaledLogits] = ()


def crop_region(
    box, width: int, height: int, params: EstimatorParams
) -> tuple[tuple[int, int, int, int], float]:
    """The region of a (width, height) px image cropped around a person box (x0, y0, x1, y1)
    px: the box with box_margin of the person's extent on every side, within the image, widened
    by beyond_edge of the extent on each side where the box reaches past it. Returns ((x0, y0,
    x1, y1) int px, the person's extent in px)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    extent = max(x1 - x0, y1 - y0) / params.box_to_extent
    margin, beyond = params.box_margin * extent, int(params.beyond_edge * extent)
    cx0 = max(int(x0 - margin), -beyond if x0 < 0 else 0)
    cy0 = max(int(y0 - margin), -beyond if y0 < 0 else 0)
    cx1 = min(int(np.ceil(x1 + margin)), width + (beyond if x1 > width else 0))
    cy1 = min(int(np.ceil(y1 + margin)), height + (beyond if y1 > height else 0))
    return (cx0, cy0, cx1, cy1), extent


def image_share(box, width: int, height: int, params: EstimatorParams) -> float:
    """The share of a (width, height) px image's area that the crop around a person box
    (crop_region) holds, in [0, 1]."""
    (x0, y0, x1, y1), _ = crop_region(box, width, height, params)
    inside = (min(x1, width) - max(x0, 0)) * (min(y1, height) - max(y0, 0))
    return inside / (width * height)


def working_crops(images: list[np.ndarray], bboxes, params: EstimatorParams) -> list[Crop]:
    """Base scale per image (H_i, W_i, 3) uint8 RGB: from its person box (x0, y0, x1, y1) px, as
    checked where it entered (ds3d.inputs), if given, else from the image size."""
    out = []
    for i, image in enumerate(images):
        box = None if bboxes is None else bboxes[i]
        h, w = image.shape[:2]
        if box is None:
            extent = max(h, w) / params.image_to_extent
            out.append(Crop(image, 0, 0, params.canonical_extent / extent))
            continue
        (cx0, cy0, cx1, cy1), extent = crop_region(box, w, h, params)
        out.append(
            Crop(_cropped(image, cx0, cy0, cx1, cy1), cx0, cy0, params.canonical_extent / extent)
        )
    return out


def _cropped(image: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """The (y1 - y0, x1 - x0, 3) region of an image at (x0, y0) px, black where it lies past the
    image's edges (crop_region's beyond_edge)."""
    h, w = image.shape[:2]
    inside = image[max(y0, 0) : min(y1, h), max(x0, 0) : min(x1, w)]
    pad = (max(-y0, 0), max(y1 - h, 0), max(-x0, 0), max(x1 - w, 0))
    if not any(pad):
        return np.ascontiguousarray(inside)
    return cv2.copyMakeBorder(inside, *pad, cv2.BORDER_CONSTANT, value=(0, 0, 0))
