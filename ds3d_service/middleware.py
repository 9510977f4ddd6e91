"""The base of the service's middlewares: plain ASGI, for HTTP requests only.

Plain ASGI rather than `app.middleware("http")`, whose call_next passes each answer through a
memory stream: an answer's head and body then reach the server in one step of the event loop, so
a replica killed under load cannot leave a balancer holding a head without its body, which it
could not send to another replica (tests/tools/test_crash.py).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Receive, Scope, Send


class HttpMiddleware:
    """Passes every request on to `app`; a subclass handles the HTTP ones in `http`."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            await self.http(scope, receive, send)
        else:
            await self.app(scope, receive, send)

    async def http(self, scope: Scope, receive: Receive, send: Send) -> None:
        """One HTTP request."""
        await self.app(scope, receive, send)
