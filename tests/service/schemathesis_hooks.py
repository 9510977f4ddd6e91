"""What an image is, for Schemathesis: /v1/pose takes image/* files, whose schema (a binary
string) cannot say that the bytes must be an image. Loaded by schemathesis.toml (the CLI, `st run`
from the repository root) and by test_contract.py: every generated image file is a real PNG."""

from __future__ import annotations

import io

import schemathesis
from hypothesis import strategies as st
from PIL import Image

from ds3d.inputs import MAX_ASPECT_RATIO


@st.composite
def png_images(draw) -> bytes:
    """PNG files of any size up to 96 px a side that the search takes (no longer than
    MAX_ASPECT_RATIO times their width), in one colour."""
    width = draw(st.integers(1, 96))
    longest = int(width * MAX_ASPECT_RATIO)
    height = draw(st.integers(max(1, -(-width // 8)), min(96, longest)))
    colour = draw(st.tuples(*[st.integers(0, 255)] * 3))
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), colour).save(buffer, "PNG")
    return buffer.getvalue()


# /v1/pose's multipart field `image` and its raw body declare image/*, which this matches.
schemathesis.openapi.media_type("image/png", png_images())
