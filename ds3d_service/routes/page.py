"""The web page to try the service: GET / (ds3d_service/static/index.html) and GET /static/{name}
(the page's script and style sheet). Plain files, no build step, nothing fetched from elsewhere:
the page calls /v1/pose of the same origin. Open without an API key (ds3d_service.access.rules);
the page asks for one where the deployment needs it."""

from __future__ import annotations

import hashlib
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import Response

from ds3d_service.errors import ApiError

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"

MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".png": "image/png",
    ".svg": "image/svg+xml",
}

# The page runs its own script and style sheet only, and talks to its own origin only: an
# injected <script> or a changed form target does nothing. blob: and data: for the user's own
# photo and webcam frames, shown without leaving the page.
PAGE_CSP = "; ".join(
    [
        "default-src 'self'",
        "script-src 'self'",
        "style-src 'self'",
        "img-src 'self' blob: data:",
        "media-src 'self' blob:",
        "connect-src 'self'",
        "frame-ancestors 'none'",
        "base-uri 'none'",
        "form-action 'none'",
    ]
)

router = APIRouter()


def static_files() -> dict[str, Path]:
    """The files /static/ serves, by name: those of ds3d_service/static with a known media type.
    Anything else (another folder, a path with a slash, a dot file) is not served."""
    return {
        path.name: path
        for path in sorted(STATIC_DIR.iterdir())
        if path.is_file() and path.suffix in MEDIA_TYPES and not path.name.startswith(".")
    }


def file_response(request: Request, path: Path) -> Response:
    """The file, revalidated on every load (no-cache with an ETag of its content: an upgraded
    service is never shown with a stale script) and answered 304 when the browser has it."""
    body = path.read_bytes()
    etag = f'"{hashlib.sha256(body).hexdigest()[:32]}"'
    headers = {
        "Cache-Control": "no-cache",
        "ETag": etag,
        "Content-Security-Policy": PAGE_CSP,
    }
    if etag in request.headers.get("if-none-match", ""):
        return Response(status_code=304, headers=headers)
    return Response(body, media_type=MEDIA_TYPES[path.suffix], headers=headers)


@router.api_route("/", methods=["GET", "HEAD"], include_in_schema=False)
async def page(request: Request) -> Response:
    """The page to try the service on one's own photo."""
    return file_response(request, STATIC_DIR / "index.html")


@router.api_route("/static/{name}", methods=["GET", "HEAD"], include_in_schema=False)
async def static(request: Request, name: str) -> Response:
    path = static_files().get(name)
    if path is None:
        raise ApiError(404, "not_found", f"no static file {name!r}")
    return file_response(request, path)
