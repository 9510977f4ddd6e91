"""Access to the service, as middleware: who calls (an API key's id, or the client address when
the service runs without keys), whether they may (the key, the request rate), a request id,
an access log line without secrets, and the headers that tell browsers what the answers are.

Open to every caller: /healthz and /readyz (probes), the web page (/ and /static/), the API's
description (/docs, /openapi.json) and the skeleton the page draws with (/v1/skeleton); /metrics
needs a key too unless `metrics_public`. Keys are never accepted in the URL.
"""

from __future__ import annotations

import logging
import re
import time
import uuid
from urllib.parse import parse_qsl

from fastapi import Request, Security
from fastapi.security import APIKeyHeader, HTTPBearer
from starlette.datastructures import MutableHeaders
from starlette.types import Message, Receive, Scope, Send

from ds3d_service.access.keys import ApiKeys, InvalidKeys, presented_key, read_keys
from ds3d_service.access.ratelimit import RequestRate, TooManyRequests
from ds3d_service.errors import ApiError, error_response
from ds3d_service.middleware import HttpMiddleware
from ds3d_service.settings import Settings

log = logging.getLogger("ds3d_service.access.rules")

# The two ways to send a key, as OpenAPI security schemes (inert: `guard` checks the key).
API_KEY_SCHEMES = [
    Security(HTTPBearer(auto_error=False, description="Authorization: Bearer KEY")),
    Security(APIKeyHeader(name="X-API-Key", auto_error=False)),
]

OPEN_PATHS = frozenset(
    {
        "/",
        "/healthz",
        "/readyz",
        "/docs",
        "/docs/oauth2-redirect",
        "/redoc",
        "/openapi.json",
        "/v1/skeleton",
    }
)
# Query parameters that look like a credential: refused, so that no key lands in a log or history.
KEY_PARAMETERS = frozenset({"api_key", "apikey", "key", "token", "access_token", "auth"})
REQUEST_ID = re.compile(r"[A-Za-z0-9._-]{1,64}")
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
}


class Access:
    """The access rules of one app: its keys (None: no keys, every caller admitted), whether
    /metrics is public, and the per-caller request rate (None: unlimited)."""

    def __init__(self, keys: ApiKeys | None, metrics_public: bool, rate: RequestRate | None):
        self.keys, self.metrics_public, self.rate = keys, metrics_public, rate

    def needs_key(self, path: str) -> bool:
        if self.keys is None or path in OPEN_PATHS or path.startswith("/static/"):
            return False
        return not (path == "/metrics" and self.metrics_public)

    def caller(self, request: Request) -> str:
        """The caller's id: `key:ID` for a valid key, else `ip:ADDRESS`. Raises ApiError 400 for
        a key in the URL, 401 when the path needs a key and none (or a wrong one) came, 429 over
        the request rate."""
        if any(name.lower() in KEY_PARAMETERS for name, _ in parse_qsl(request.url.query)):
            raise ApiError(
                400,
                "key_in_url",
                "send the API key in the Authorization or X-API-Key header, never in the URL",
            )
        caller = f"ip:{request.client.host if request.client else 'unknown'}"
        if self.needs_key(request.url.path):
            key = presented_key(request.headers)
            found = self.keys.check(key) if key is not None and self.keys is not None else None
            if found is None:
                what = "no API key" if key is None else "a wrong API key"
                challenge = {"WWW-Authenticate": 'Bearer realm="ds3d"'}
                raise ApiError(
                    401,
                    "unauthorized",
                    f"{what}: send Authorization: Bearer KEY or X-API-Key: KEY",
                    challenge,
                )
            caller = f"key:{found}"
        if self.rate is not None and request.url.path.startswith("/v1/"):
            try:
                self.rate.take(caller)
            except TooManyRequests as exc:
                retry = {"Retry-After": str(max(1, round(exc.retry_after_s)))}
                raise ApiError(429, "rate_limited", str(exc), retry) from None
        return caller


def access_rules(settings: Settings) -> Access:
    """The Access of `settings`; raises InvalidKeys for unusable keys, or for none when
    require_api_keys is set."""
    keys = None
    if settings.api_keys is not None:
        keys = ApiKeys(read_keys(settings.api_keys.get_secret_value()))
    elif settings.require_api_keys:
        raise InvalidKeys(
            "require_api_keys is set and api_keys is not: give DS3D_API_KEYS (keys, or a file "
            "of keys) or unset DS3D_REQUIRE_API_KEYS to serve every caller"
        )
    rate = None
    if settings.rate_limit_rps > 0:
        rate = RequestRate(settings.rate_limit_rps, settings.rate_limit_burst)
    return Access(keys, settings.metrics_public, rate)


def describe(access: Access, settings: Settings) -> str:
    """The startup log line on who may call."""
    if access.keys is None:
        return f"no API keys: open to every caller that can reach {settings.host}:{settings.port}"
    metrics = "open" if access.metrics_public else "with a key"
    count = f"{len(access.keys)} API key" + ("s" if len(access.keys) > 1 else "")
    return f"{count}; /v1/* need one (/v1/skeleton aside), /metrics {metrics}"


def request_id(request: Request) -> str:
    """The client's X-Request-ID when it is a short plain token, else a new one."""
    given = request.headers.get("x-request-id", "")
    return given if REQUEST_ID.fullmatch(given) else uuid.uuid4().hex


class Guard(HttpMiddleware):
    """Middleware: the request id, the caller (request.state.caller) or its refusal, the browser
    headers, and one access log line (method, path without the query, status, ms, caller)."""

    async def http(self, scope: Scope, receive: Receive, send: Send) -> None:
        t0 = time.perf_counter()
        request = Request(scope)
        rid = request.state.request_id = request_id(request)
        status = 500  # when the app raises before it answers (the metrics middleware answers)

        async def send_marked(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                headers = MutableHeaders(scope=message)
                headers["X-Request-ID"] = rid
                for name, value in SECURITY_HEADERS.items():
                    headers.setdefault(name, value)
            await send(message)

        try:
            request.state.caller = caller = scope["app"].state.access.caller(request)
        except ApiError as refusal:
            caller = "refused"
            await error_response(refusal)(scope, receive, send_marked)
        else:
            await self.app(scope, receive, send_marked)
        log.info(
            "%s %s %s %d %.1f ms %s",
            rid,
            request.method,
            request.url.path,
            status,
            1000 * (time.perf_counter() - t0),
            caller,
        )
