"""Every error the service answers is JSON `{"error": {"code", "message"[, "details"]}}`.
This module maps the library's typed errors (one table, LIBRARY_ERRORS), the model queues' and
the framework's to status codes."""

from __future__ import annotations

import logging
from collections.abc import Mapping

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from ds3d.errors import (
    DataFormatError,
    Ds3dError,
    ImageTooLarge,
    InvalidBox,
    InvalidImage,
    InvalidPose,
)
from ds3d_service.microbatch import (
    CallerQueueFull,
    DeadlineExceeded,
    ItemFailed,
    QueueError,
    QueueFull,
    ShuttingDown,
)

log = logging.getLogger("ds3d_service")


class ApiError(Exception):
    """An error answer: HTTP status, stable code, human message, optional extra headers."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        headers: Mapping[str, str] | None = None,
        details: list[dict] | None = None,
    ):
        super().__init__(message)
        self.status, self.code, self.message = status, code, message
        self.headers, self.details = headers, details


def error_response(err: ApiError) -> JSONResponse:
    body: dict = {"code": err.code, "message": err.message}
    if err.details:
        body["details"] = err.details
    return JSONResponse({"error": body}, status_code=err.status, headers=err.headers)


# Each of the library's errors as (status, code), looked up most specific first (a subclass
# not listed is answered as its nearest base). A 5xx is the service's own fault (DataFormatError:
# its models): logged and answered as `internal`, without the error's text.
LIBRARY_ERRORS: dict[type[Ds3dError], tuple[int, str]] = {
    InvalidPose: (422, "invalid_pose"),
    InvalidBox: (422, "invalid_box"),
    InvalidImage: (422, "invalid_image"),
    ImageTooLarge: (422, "invalid_image"),
    DataFormatError: (500, "internal"),
    Ds3dError: (500, "internal"),
}


def library_answer(kind: type[Ds3dError]) -> tuple[int, str]:
    """LIBRARY_ERRORS' (status, code) for `kind`: its own, else that of its nearest base."""
    return next(LIBRARY_ERRORS[base] for base in kind.__mro__ if base in LIBRARY_ERRORS)


def to_api_error(exc: BaseException, retry_after_s: int) -> ApiError:
    """The answer for an exception raised while serving a request."""
    retry = {"Retry-After": str(retry_after_s)}
    if isinstance(exc, ApiError):
        return exc
    if isinstance(exc, ItemFailed):
        inner = to_api_error(exc.cause, retry_after_s)
        inner.message = f"items[{exc.index}]: {inner.message}"
        return inner
    if isinstance(exc, CallerQueueFull):
        message = f"this caller's share of the queue is full ({exc}, caller_queue_share)"
        return ApiError(429, "caller_queue_full", message, retry)
    if isinstance(exc, QueueFull):
        message = f"the queue is full ({exc}: max_queue, max_lift_queue); retry later"
        return ApiError(503, "overloaded", message, retry)
    if isinstance(exc, ShuttingDown):
        return ApiError(503, "shutting_down", str(exc), retry)
    if isinstance(exc, DeadlineExceeded):
        return ApiError(504, "timeout", f"the request timed out: {exc} (request_timeout_s)")
    if isinstance(exc, Ds3dError):
        status, code = library_answer(type(exc))
        if status < 500:
            return ApiError(status, code, str(exc))
    log.exception("unexpected error", exc_info=exc)
    return ApiError(500, "internal", f"internal error: {type(exc).__name__}")


_HTTP_CODES = {
    400: "bad_request",
    404: "not_found",
    405: "method_not_allowed",
    413: "payload_too_large",
    415: "unsupported_media_type",
}


def install_handlers(app: FastAPI, retry_after_s: int) -> None:
    """Answer every error of `app` in the JSON error shape."""

    @app.exception_handler(ApiError)
    async def _api(_: Request, exc: ApiError):
        return error_response(exc)

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError):
        errors = exc.errors()
        if any(e.get("type") == "json_invalid" for e in errors):
            return error_response(ApiError(422, "invalid_json", "the body is not valid JSON"))
        details = [
            {
                "loc": [str(p) for p in e.get("loc", ())],
                "msg": e.get("msg", ""),
                "type": e.get("type"),
            }
            for e in errors[:20]
        ]
        first = details[0] if details else {"loc": [], "msg": "invalid request"}
        message = f"{'.'.join(first['loc'])}: {first['msg']}"
        return error_response(ApiError(422, "invalid_request", message, details=details))

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
        return error_response(ApiError(exc.status_code, code, str(exc.detail), exc.headers))

    async def _mapped(_: Request, exc: Exception):
        return error_response(to_api_error(exc, retry_after_s))

    # Each base once: the library's errors by LIBRARY_ERRORS, the model queues' by to_api_error.
    for kind in (Ds3dError, QueueError):
        app.add_exception_handler(kind, _mapped)
