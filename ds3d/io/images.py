"""Decode untrusted image bytes or files to RGB uint8 arrays, refusing anything suspicious.

The header is read first and the pixel count checked BEFORE any pixel is decoded, so a small
file that claims a huge size (a decompression bomb) costs nothing. Empty, non-image, corrupt and
truncated inputs raise ds3d.errors.InvalidImage.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from ds3d.errors import ImageTooLarge, InvalidImage

# 40 megapixels: far above any photo the pose estimator needs, far below a bomb.
DEFAULT_MAX_PIXELS = 40_000_000


def decode_image(data: bytes, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Image file bytes (JPEG, PNG, BMP, WebP, ...) -> (H, W, 3) uint8 RGB, upright by the
    EXIF orientation tag where there is one.

    Raises InvalidImage if the bytes are empty, not an image, corrupt or truncated, and its
    subclass ImageTooLarge if the header claims more than max_pixels pixels (checked before
    decoding).
    """
    if not data:
        raise InvalidImage("empty image")
    try:
        with warnings.catch_warnings():
            # PIL warns (and past 2x its own limit raises) on huge headers; we apply our limit.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(data))
            width, height = img.size
            if width <= 0 or height <= 0:
                raise InvalidImage(f"image has no pixels ({width}x{height})")
            if width * height > max_pixels:
                raise ImageTooLarge(
                    f"image is {width}x{height} = {width * height} pixels, "
                    f"more than the limit of {max_pixels}"
                )
            img.load()  # raises OSError on truncated or corrupt data
            # as the photo was taken: a phone's JPEG stores its pixels as the sensor read them
            # and says how to turn them in the EXIF orientation tag
            rgb = ImageOps.exif_transpose(img).convert("RGB")
    except InvalidImage:
        raise
    except Image.DecompressionBombError as exc:
        raise ImageTooLarge(f"image has more than the limit of {max_pixels} pixels: {exc}") from exc
    except UnidentifiedImageError as exc:
        raise InvalidImage("not an image, or an unsupported format") from exc
    except (OSError, SyntaxError, ValueError) as exc:
        raise InvalidImage(f"corrupt or truncated image: {exc}") from exc
    return np.array(rgb, dtype=np.uint8)  # a writable copy


def read_image(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Image file at path -> (H, W, 3) uint8 RGB; InvalidImage as decode_image (or if missing)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InvalidImage(f"cannot read {path}: {exc}") from exc
    return decode_image(data, max_pixels=max_pixels)
