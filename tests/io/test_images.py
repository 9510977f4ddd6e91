"""Decoding untrusted images: good files decode, everything else raises InvalidImage."""

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from ds3d.errors import InvalidImage
from ds3d.io.images import decode_image, read_image


def _encode(array: np.ndarray, fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format=fmt)
    return buf.getvalue()


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG whose IHDR claims width x height, with a tiny (invalid) body."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 16))


@pytest.mark.parametrize("fmt", ["PNG", "BMP"])
def test_lossless_formats_decode_exactly(fmt):
    rgb = np.random.default_rng(0).integers(0, 256, (21, 34, 3), dtype=np.uint8)
    out = decode_image(_encode(rgb, fmt))
    assert out.dtype == np.uint8 and out.shape == (21, 34, 3)
    np.testing.assert_array_equal(out, rgb)
    assert out.flags.writeable


def test_jpeg_grey_and_rgba_become_rgb():
    rgb = np.full((16, 16, 3), 120, dtype=np.uint8)
    assert np.abs(decode_image(_encode(rgb, "JPEG")).astype(int) - 120).max() <= 2
    grey = decode_image(_encode(np.full((5, 7), 9, dtype=np.uint8), "PNG"))
    assert grey.shape == (5, 7, 3) and (grey == 9).all()
    rgba = decode_image(_encode(np.zeros((4, 4, 4), dtype=np.uint8), "PNG"))
    assert rgba.shape == (4, 4, 3)


@pytest.mark.parametrize(
    "data",
    [b"", b"hello, this is not an image", b"\x89PNG\r\n\x1a\n" + b"\0" * 40, b"\xff\xd8\xff"],
    ids=["empty", "text", "broken-png", "jpeg-magic-only"],
)
def test_garbage_is_refused(data):
    with pytest.raises(InvalidImage):
        decode_image(data)


def test_truncated_files_are_refused():
    rgb = np.random.default_rng(1).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    for fmt in ("PNG", "JPEG"):
        data = _encode(rgb, fmt)
        with pytest.raises(InvalidImage):
            decode_image(data[: len(data) // 2])


def test_huge_header_is_refused_before_decoding():
    # 50,000 x 50,000 claimed by a 60-byte file: refused from the header alone.
    with pytest.raises(InvalidImage, match="limit"):
        decode_image(_png_header_only(50_000, 50_000))
    rgb = np.zeros((100, 100, 3), dtype=np.uint8)
    with pytest.raises(InvalidImage, match="limit"):
        decode_image(_encode(rgb, "PNG"), max_pixels=9_999)
    assert decode_image(_encode(rgb, "PNG"), max_pixels=10_000).shape == (100, 100, 3)


def test_read_image_from_paths(tmp_path):
    good = tmp_path / "a.png"
    good.write_bytes(_encode(np.zeros((3, 5, 3), dtype=np.uint8), "PNG"))
    assert read_image(good).shape == (3, 5, 3)
    (tmp_path / "empty.jpg").write_bytes(b"")
    for bad in (tmp_path / "empty.jpg", tmp_path / "missing.png", tmp_path):
        with pytest.raises(InvalidImage):
            read_image(bad)


def test_exif_orientation_6_is_applied():
    """A phone JPEG stored landscape with orientation 6 ("rotate 90 clockwise to view") decodes
    portrait, its top-left marker at the top right."""
    stored = np.zeros((40, 60, 3), np.uint8)
    stored[:10, :10] = 255  # stored top-left corner
    exif = Image.Exif()
    exif[0x0112] = 6
    buf = io.BytesIO()
    Image.fromarray(stored).save(buf, format="JPEG", quality=95, exif=exif.tobytes())
    upright = decode_image(buf.getvalue())
    assert upright.shape == (60, 40, 3)
    assert upright[:10, -10:].mean() > 200 and upright[:10, :10].mean() < 50
