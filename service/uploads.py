"""Reading the /v1/pose upload into a PoseInput: the image as multipart field `image` or as a raw
image/* body, within the size caps, the optional bbox and intrinsics (form fields or query
parameters), and the decoded image. Every check here runs before the model is consulted."""

from __future__ import annotations

import json

import numpy as np
from fastapi import Request
from fastapi.concurrency import run_in_threadpool
from starlette.datastructures import FormData, UploadFile

from ds3d.boxes import checked_box
from ds3d.errors import ImageTooLarge
from ds3d.image_io import decode_image
from service.engine import PoseInput
from service.errors import ApiError
from service.settings import Settings

# Room for the multipart envelope and the small form fields around the image.
MULTIPART_OVERHEAD_BYTES = 64 * 1024

# The OpenAPI request body of /v1/pose: the route reads the body itself (below), so FastAPI
# cannot infer it.
POSE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["image"],
                    "properties": {
                        "image": {"type": "string", "format": "binary"},
                        "bbox": {"type": "string", "description": "JSON [x0, y0, x1, y1] px"},
                        "intrinsics": {"type": "string", "description": "JSON 3x3 matrix"},
                    },
                }
            },
            "image/*": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


async def read_pose_input(
    request: Request, settings: Settings, bbox: str | None, intrinsics: str | None
) -> PoseInput:
    """The image, box and intrinsics of a /v1/pose request. bbox, intrinsics: the query
    parameters (JSON text), which multipart form fields of the same names override. Raises
    ApiError 413 (too large), 415 (not an image content type), 422 (missing field, bad array),
    InvalidImage (an image that does not decode) or InvalidBox (a box the image cannot hold)."""
    limit = settings.max_image_bytes
    ctype = request.headers.get("content-type", "").lower()
    _refuse_declared_oversize(request, limit)
    if ctype.startswith("multipart/form-data"):
        form = await request.form(max_files=1, max_fields=8)
        data = await _read_form_image(form, limit)
        bbox = _form_text(form, "bbox", bbox)
        intrinsics = _form_text(form, "intrinsics", intrinsics)
    else:
        _require_image_type(ctype)
        data = await _read_capped_body(request, limit)
    box = parse_array(bbox, (4,), "bbox")
    k = parse_array(intrinsics, (3, 3), "intrinsics")
    try:
        image = await run_in_threadpool(decode_image, data, settings.max_image_pixels)
    except ImageTooLarge as exc:
        raise ApiError(422, "invalid_image", f"{exc} (max_image_pixels)") from exc
    if box is not None:
        box = checked_box(box, image.shape[1], image.shape[0])
    return PoseInput(image, box, k)


def too_large(what: str, limit: int) -> ApiError:
    """413, naming the setting that set the limit."""
    return ApiError(413, "payload_too_large", f"{what} is over max_image_bytes = {limit} bytes")


def _refuse_declared_oversize(request: Request, image_limit: int) -> None:
    """413 before reading, when the Content-Length already says the body is over the image limit
    (plus room for a multipart envelope)."""
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > image_limit + MULTIPART_OVERHEAD_BYTES:
        raise too_large("the body", image_limit)


async def _read_form_image(form: FormData, limit: int) -> bytes:
    """The bytes of the multipart file field `image`, at most `limit` of them."""
    upload = form.get("image")
    if not isinstance(upload, UploadFile):
        raise ApiError(422, "invalid_request", "multipart field 'image' (a file) missing")
    if upload.size is not None and upload.size > limit:
        raise too_large("the image", limit)
    return await upload.read()


def _form_text(form: FormData, name: str, default: str | None) -> str | None:
    """Text field `name` of the form, else `default` (a file under that name does not count)."""
    value = form.get(name)
    return value if isinstance(value, str) else default


def _require_image_type(ctype: str) -> None:
    if not ctype.startswith("image/"):
        hint = "send the image as multipart field 'image' or a raw image/* body"
        raise ApiError(415, "unsupported_media_type", hint)


async def _read_capped_body(request: Request, limit: int) -> bytes:
    """The raw body, refused with 413 as soon as it passes `limit` bytes."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large("the image", limit)
        chunks.append(chunk)
    return b"".join(chunks)


def parse_array(text: str | None, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    """A JSON array form field or query parameter -> float32 array of `shape`, or None."""
    if text is None or text == "":
        return None
    try:
        arr = np.asarray(json.loads(text), dtype=np.float32)
    except (ValueError, TypeError) as e:
        raise ApiError(422, "invalid_request", f"{name}: not a JSON array of numbers") from e
    if arr.shape != shape or not np.isfinite(arr).all():
        raise ApiError(422, "invalid_request", f"{name}: need finite numbers of shape {shape}")
    return arr
