"""Reading the /v1/pose upload into a checked ImageInput (ds3d.inputs.image_input): the image as
multipart field `image` or as a raw image/* body, within the size caps, the optional person box
and intrinsics (form fields or query parameters), and the decoded image. Every check here runs
before the model is consulted.

The person box is `box`, a PersonBox (its centre and sides as fractions of the image), whose
schema says every rule it has: the corner form `bbox` [x0, y0, x1, y1] px of earlier clients is
still read, but left out of the OpenAPI document, since no schema can say x1 > x0 or that the
box overlaps an image it has not seen, and a client generated from the document would send boxes
that it allows and the service refuses."""

from __future__ import annotations

from typing import TypeVar

from fastapi import Request
from fastapi.concurrency import run_in_threadpool
from pydantic import TypeAdapter, ValidationError
from starlette.datastructures import FormData, UploadFile

from ds3d.errors import ImageTooLarge
from ds3d.inputs import ImageInput, image_input
from ds3d.io.images import decode_image
from ds3d_service.errors import ApiError
from ds3d_service.schemas import Corners, Intrinsics, PersonBox
from ds3d_service.settings import Settings

T = TypeVar("T")

# The JSON-valued options (bbox, the corner form of box, outside the OpenAPI document), query
# parameters or form fields; the form's fields are the image and these.
JSON_FIELDS = ("box", "bbox", "intrinsics")
FORM_FIELDS = ("image", *JSON_FIELDS)

# Room for the multipart envelope and the small form fields around the image.
MULTIPART_OVERHEAD_BYTES = 64 * 1024

# The box and the intrinsics of /v1/pose travel as JSON text (query parameters or form fields);
# their schemas are those of /v1/lift's values.
BOX = TypeAdapter(PersonBox)
CORNERS = TypeAdapter(Corners)
INTRINSICS = TypeAdapter(Intrinsics)
BOX_DOC = (
    "the person's box, as fractions of the image's width and height: its centre cx, cy in [0, 1]"
    " and its width and height; skips the search"
)
INTRINSICS_DOC = "3x3 camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] px"


def _json_text(adapter: TypeAdapter, description: str) -> dict:
    return {"description": description, **adapter.json_schema()}


# The OpenAPI of /v1/pose's JSON-valued parameters and its body: the route reads them itself
# (below), so FastAPI cannot infer them.
POSE_OPENAPI = {
    "parameters": [
        {
            "name": name,
            "in": "query",
            "required": False,
            "content": {"application/json": {"schema": _json_text(adapter, doc)}},
        }
        for name, adapter, doc in (
            ("box", BOX, BOX_DOC),
            ("intrinsics", INTRINSICS, INTRINSICS_DOC),
        )
    ],
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["image"],
                    "additionalProperties": False,
                    "properties": {
                        "image": {"type": "string", "format": "binary"},
                        "box": _json_text(BOX, BOX_DOC),
                        "intrinsics": _json_text(INTRINSICS, INTRINSICS_DOC),
                    },
                },
                "encoding": {
                    "image": {"contentType": "image/*"},
                    "box": {"contentType": "application/json"},
                    "intrinsics": {"contentType": "application/json"},
                },
            },
            "image/*": {"schema": {"type": "string", "format": "binary"}},
        },
    },
}


async def read_pose_input(request: Request, settings: Settings, **options) -> ImageInput:
    """The image, box and intrinsics of a /v1/pose request, checked with `options` (focal_px,
    people, min_score) by ds3d.inputs.image_input. box (or the corner form bbox), intrinsics:
    JSON text in the query parameters, which multipart form fields of the same names override.
    Raises ApiError 413 (too large), 415 (not an image content type), 422 (missing field, bad
    JSON, both box and bbox), or image_input's errors (an image that does not decode, a box it
    cannot hold, ...)."""
    limit = settings.max_image_bytes
    ctype = request.headers.get("content-type", "").lower()
    texts = {name: request.query_params.get(name) for name in JSON_FIELDS}
    _refuse_declared_oversize(request, limit)
    if ctype.startswith("multipart/form-data"):
        form = await request.form(max_files=1, max_fields=8)
        _refuse_unknown_fields(form)
        data = await _read_form_image(form, limit)
        texts = {name: _form_text(form, name, text) for name, text in texts.items()}
    else:
        _require_image_type(ctype)
        data = await _read_capped_body(request, limit)
    box = parse_json(texts["box"], BOX, "box")
    corners = parse_json(texts["bbox"], CORNERS, "bbox")
    if box is not None and corners is not None:
        raise ApiError(422, "invalid_request", "give the person's box once: box or bbox")
    k = parse_json(texts["intrinsics"], INTRINSICS, "intrinsics")
    try:
        image = await run_in_threadpool(decode_image, data, settings.max_image_pixels)
    except ImageTooLarge as exc:
        raise ApiError(422, "invalid_image", f"{exc} (max_image_pixels)") from exc
    height, width = image.shape[:2]
    bbox = corners if box is None else box.corners(width, height)
    return image_input(image, bbox, k, **options)


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


def _refuse_unknown_fields(form: FormData) -> None:
    """422 for a form field /v1/pose does not read (its document says the form has no others):
    a field misnamed, or an option sent in the form that is read from the query, would
    otherwise be left out without a word."""
    unknown = sorted(set(form.keys()) - set(FORM_FIELDS))
    if unknown:
        known = ", ".join(name for name in FORM_FIELDS if name != "bbox")
        raise ApiError(
            422, "invalid_request", f"unknown form fields {unknown}: the form has {known}"
        )


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


def parse_json(text: str | None, adapter: TypeAdapter[T], name: str) -> T | None:
    """A JSON form field or query parameter validated by `adapter`, or None when absent; 422
    invalid_request naming what is wrong."""
    if text is None or text == "":
        return None
    try:
        return adapter.validate_json(text)
    except ValidationError as e:
        first = e.errors()[0]
        where = "".join(f"[{p}]" for p in first["loc"])
        raise ApiError(422, "invalid_request", f"{name}{where}: {first['msg']}") from e
