"""Validation of what users give the library, at its edge: images, person boxes, poses and
cameras (shapes, dtypes, finite values within MAX_COORDINATE_PX), and the options of an image's
answer. Each input is checked once, where it enters: `image_input` for an image to estimate (the
Python API, `ds3d predict`, `ds3d batch` and the service all make theirs with it), the *_batch
functions for 2D poses to lift. Everything past this point may assume well-formed inputs."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ds3d.errors import InvalidBox, InvalidImage, InvalidPose
from ds3d.skeleton import NUM_JOINTS

# The largest magnitude of a 2D coordinate or a camera matrix entry, px: far beyond any image
# (a 40-megapixel photo's side is below 1e5), and small enough that the fits' squared
# residuals stay finite in float32 (1e30 px squared overflows it, and the energy became NaN).
MAX_COORDINATE_PX = 1e7
# The shortest focal length taken, px: below it a camera would see more than a half-space of a
# few-pixel image; in float32 a tinier positive one may round to zero.
MIN_FOCAL_PX = 1.0
# The longest side of an image searched for people, in multiples of its shortest. Every level of
# the search scales the image height to about the same number of px, so a level's pixels grow
# with the ratio and its PSM's max-convolution with the ratio squared: without a bound, one 8 x
# 8000 strip asked for 800 GB. An image with a person box needs no search.
MAX_ASPECT_RATIO = 8.0
# A person box's sides are taken as at least MIN_BOX_PX, widened about its centre: the 2D stage
# scales a box to its canonical extent (100 px), and a box of a thousandth of a pixel asked for a
# crop of 30 GB.
MIN_BOX_PX = 1.0
# The longest side a person box may have, in multiples of its image's longer side: the 2D stage
# cuts the crop out at the image's resolution, padding it past the image's edges by up to
# beyond_edge of the box's size, before scaling it; a 100,000 px box on a 640 x 480 photo asked
# for 3 GB of padding and a minute. Four times holds a photo of a person's head and shoulders
# with the box of all of them.
MAX_BOX_SCALE = 4.0
PEOPLE = ("best", "all")  # who an image answers: its best person, or every one found
# The default min_score: people less likely than this are not answered. The score is a
# calibrated probability (ds3d.people.score; docs/RESULTS.md, people in photos): answered where
# more likely a person than not.
MIN_SCORE = 0.5


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


@dataclass(frozen=True)
class PoseInput:
    """One 2D pose to lift, checked (pose_input): joints_2d (14, 2) float32 px, LSP order;
    visible (14,) bool, at least two; intrinsics (3, 3) float32 or None (weak perspective)."""

    joints_2d: np.ndarray
    visible: np.ndarray
    intrinsics: np.ndarray | None = None


def pose_input(joints_2d, visible=None, intrinsics=None) -> PoseInput:
    """The one check of a 2D pose to lift (joints_2d_batch, visibility_batch, intrinsics_batch
    of one pose); raises InvalidPose."""
    x = joints_2d_batch(joints_2d)
    if len(x) != 1:
        raise InvalidPose(f"joints_2d: expected one pose (14, 2), got {tuple(x.shape)}")
    k = intrinsics_batch(intrinsics, 1)
    return PoseInput(
        x[0].numpy(), visibility_batch(visible, 1)[0].numpy(), None if k is None else k[0].numpy()
    )


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


def checked_image(image) -> np.ndarray:
    """An image as the library takes it: (H, W, 3) uint8 RGB with H, W >= 1; raises
    InvalidImage."""
    if not isinstance(image, np.ndarray):
        raise InvalidImage(f"an image must be a NumPy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8 or 0 in image.shape:
        raise InvalidImage(f"an image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    return image


def checked_box(box, width: int, height: int) -> np.ndarray:
    """A person box given by a user, (x0, y0, x1, y1) px, checked against its image of width x
    height px -> (4,) float32. The one place where the CLI, the Python API and the service
    refuse a box: raises InvalidBox, naming why, when it is not four finite numbers, its corners
    are reversed or it has no area, it does not overlap the image, or its longer side is over
    MAX_BOX_SCALE times the image's. A box that overlaps the image only in part is kept (the 2D
    stage crops what lies inside); a side under MIN_BOX_PX is widened to it about its centre."""
    try:
        values = np.asarray(box, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise InvalidBox(f"bbox must be four numbers x0, y0, x1, y1; got {box!r}") from err
    if values.size != 4:
        raise InvalidBox(f"bbox must be four numbers x0, y0, x1, y1; got {values.size}")
    if not np.isfinite(values).all():
        raise InvalidBox("bbox has a NaN or infinite coordinate")
    x0, y0, x1, y1 = (float(v) for v in values)
    if x1 <= x0 or y1 <= y0:
        raise InvalidBox(
            f"bbox [{x0:g}, {y0:g}, {x1:g}, {y1:g}] has no area: it wants x1 > x0 and y1 > y0 "
            "(corners x0, y0, x1, y1, not x, y, width, height)"
        )
    x0, x1 = _at_least(x0, x1, MIN_BOX_PX)
    y0, y1 = _at_least(y0, y1, MIN_BOX_PX)
    if x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        raise InvalidBox(
            f"bbox [{x0:g}, {y0:g}, {x1:g}, {y1:g}] lies outside the {width}x{height} image"
        )
    if max(x1 - x0, y1 - y0) > MAX_BOX_SCALE * max(width, height):
        raise InvalidBox(
            f"bbox [{x0:g}, {y0:g}, {x1:g}, {y1:g}] is over {MAX_BOX_SCALE:g} times the size of "
            f"the {width}x{height} image"
        )
    return np.array([x0, y0, x1, y1], np.float32)


def _at_least(low: float, high: float, size: float) -> tuple[float, float]:
    """The interval [low, high] widened about its centre to `size` where it is shorter."""
    if high - low >= size:
        return low, high
    centre = (low + high) / 2
    return centre - size / 2, centre + size / 2


def check_searchable(height: int, width: int) -> None:
    """Raises InvalidImage for an image (height, width px) too elongated to search for people
    (MAX_ASPECT_RATIO)."""
    ratio = max(height, width) / max(min(height, width), 1)
    if ratio > MAX_ASPECT_RATIO:
        raise InvalidImage(
            f"a {width} x {height} image is {ratio:.3g} times as long as it is wide, over "
            f"max_aspect_ratio = {MAX_ASPECT_RATIO:g} of the search for people: "
            "crop it, or give the person's box"
        )


@dataclass(frozen=True)
class ImageInput:
    """One image to estimate and what its answer asks, checked (image_input): image (H, W, 3)
    uint8 RGB; bbox (4,) float32 x0, y0, x1, y1 px or None (search it for people); intrinsics
    (3, 3) float32 or None; focal_px, without intrinsics, the camera's focal length (None: an
    assumed one); people "best" or "all" (PEOPLE); min_score in [0, 1]."""

    image: np.ndarray
    bbox: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    focal_px: float | None = None
    people: str = "best"
    min_score: float = MIN_SCORE


def image_input(
    image,
    bbox=None,
    intrinsics=None,
    focal_px=None,
    people: str = "best",
    min_score: float = MIN_SCORE,
) -> ImageInput:
    """The one check of an image and its options (fields as ImageInput). Raises InvalidImage (not
    an image, or without a box too elongated to search), InvalidBox (checked_box), InvalidPose
    (intrinsics or focal_px not a camera's) or ValueError (people or min_score)."""
    image = checked_image(image)
    height, width = image.shape[:2]
    if bbox is None:
        check_searchable(height, width)
    else:
        bbox = checked_box(bbox, width, height)
    k = intrinsics_batch(intrinsics, 1)
    if people not in PEOPLE:
        raise ValueError(f"people must be one of {PEOPLE}, got {people!r}")
    if not 0.0 <= min_score <= 1.0:  # NaN fails too
        raise ValueError(f"min_score must lie in [0, 1], got {min_score}")
    focal = None if focal_px is None else focal_length(focal_px)
    camera = None if k is None else k[0].numpy()
    return ImageInput(image, bbox, camera, focal, people, float(min_score))


def image_inputs(
    images,
    bboxes=None,
    intrinsics=None,
    focal_px=None,
    people: str | Sequence[str] = "best",
    min_score: float | Sequence[float] = MIN_SCORE,
) -> list[ImageInput]:
    """image_input of B images, each option given once for all of them or once per image
    (bboxes: None or B entries, each None or a box; intrinsics: None, one (3, 3) for all, or B
    entries, each None or a (3, 3))."""
    images = list(images)
    n = len(images)
    if intrinsics is not None and _one_camera(intrinsics):
        intrinsics = [intrinsics] * n
    options = zip(
        _per_image(bboxes, n, "bboxes", listed=True),
        _per_image(intrinsics, n, "intrinsics", listed=True),
        _per_image(focal_px, n, "focal_px"),
        _per_image(people, n, "people"),
        _per_image(min_score, n, "min_score"),
        strict=True,
    )
    return [image_input(image, *rest) for image, rest in zip(images, options, strict=True)]


def _per_image(value, n: int, name: str, listed: bool = False) -> list:
    """An option given once for every image (None, a str or a number; with `listed`, only None)
    or as n values."""
    if value is None or (not listed and isinstance(value, str | int | float)):
        return [value] * n
    values = list(value)
    if len(values) != n:
        raise ValueError(f"{len(values)} values of {name} for {n} images")
    return values


def _one_camera(intrinsics) -> bool:
    """Whether intrinsics are one (3, 3) matrix, rather than one entry per image."""
    try:
        return tuple(np.shape(intrinsics)) == (3, 3)
    except ValueError:  # entries of several shapes (None among matrices): one per image
        return False
