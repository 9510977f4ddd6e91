"""The app factory: `create_app(settings, engine)` wires the settings and metrics into app.state,
the lifespan that loads the models and runs the batchers, the request-metrics middleware, the JSON
error handlers and the routers of ds3d_service/routes/."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from functools import partial
from typing import Any

import torch
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from starlette.types import Message, Receive, Scope, Send

from ds3d_service.access.rules import API_KEY_SCHEMES, Guard, access_rules
from ds3d_service.access.rules import describe as describe_access
from ds3d_service.allocator import describe as describe_allocator
from ds3d_service.deps import Runtime
from ds3d_service.engine import Engine
from ds3d_service.errors import ApiError, error_response, install_handlers, to_api_error
from ds3d_service.metrics import Metrics
from ds3d_service.microbatch import MicroBatcher
from ds3d_service.middleware import HttpMiddleware
from ds3d_service.routes import API_ROUTERS, ROUTERS
from ds3d_service.settings import Settings

log = logging.getLogger("ds3d_service")


def create_app(settings: Settings | None = None, engine: Engine | None = None) -> FastAPI:
    """The app for `settings` (default: from the environment). `engine`: already loaded models
    to serve instead of loading settings.model_dir at startup (several apps may share one)."""
    settings = settings or Settings()
    app = FastAPI(
        title="ds3d",
        version="0.1.0",
        description="3D human pose from a single image (dual-source approach, Yasin et al. "
        "CVPR 2016). 2D joints in pixels, 3D joints in millimetres, 14 joints in LSP order.",
        lifespan=serving_lifespan(engine),
    )
    app.state.settings = settings
    app.state.metrics = Metrics()
    app.state.access = access_rules(settings)
    install_handlers(app, settings.retry_after_s)
    # The last added runs first: CORS answers preflights, then every request is counted, then
    # its caller is found (or refused), then its head size checked.
    app.add_middleware(RefuseLargeHead)
    app.add_middleware(Guard)
    app.add_middleware(ObserveRequests)
    if origins := [o.strip() for o in settings.cors_origins.split(",") if o.strip()]:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["GET", "POST"],
            allow_headers=["Authorization", "X-API-Key", "Content-Type", "X-Request-ID"],
            expose_headers=["X-Request-ID", "Retry-After"],
            max_age=600,
        )
    # The keys are checked by ds3d_service.access.rules.guard; the schemes declare them in the
    # OpenAPI, so that /docs offers to send one.
    schemes = API_KEY_SCHEMES if app.state.access.keys is not None else []
    for router in ROUTERS:
        app.include_router(router, dependencies=schemes if router in API_ROUTERS else [])
    app.openapi = partial(openapi_with_limits, app, settings)  # type: ignore[method-assign]
    return app


def openapi_with_limits(app: FastAPI, settings: Settings) -> dict[str, Any]:
    """The app's OpenAPI document with the limits that its settings set, so that clients
    generated from it know them: the items of one /v1/lift request."""
    schema = app.openapi_schema
    if schema is None:
        schema = FastAPI.openapi(app)  # made once and kept as app.openapi_schema
        items = schema["components"]["schemas"]["LiftRequest"]["properties"]["items"]
        items["maxItems"] = min(settings.max_lift_items, settings.max_lift_queue)
    return schema


def serving_lifespan(
    preloaded: Engine | None,
) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The app's lifespan: at startup load the models (unless `preloaded`) on the one model
    thread and start the batchers (app.state.runtime); at shutdown drain their queues."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        settings: Settings = app.state.settings
        metrics: Metrics = app.state.metrics
        torch.set_num_threads(settings.torch_threads)
        executor = model_executor(settings.torch_threads)
        engine = preloaded
        if engine is None:
            load = partial(
                Engine.load,
                settings.model_dir,
                settings.device,
                settings.workers,
                settings.torch_threads,
            )
            engine = await asyncio.get_running_loop().run_in_executor(executor, load)
        engine.on_timings = metrics.observe_stages
        runtime = start_batchers(engine, executor, settings, metrics)
        app.state.runtime = runtime
        log.info(
            "model %s loaded; serving; %s; %s",
            engine.model_id,
            describe_access(app.state.access, settings),
            describe_allocator(settings.allocator),
        )
        yield
        # Uvicorn has stopped taking requests; finish what is queued, then stop.
        for batcher in (runtime.lift, runtime.pose):
            if batcher is not None:
                await batcher.close(drain_timeout_s=settings.request_timeout_s)
        executor.shutdown(wait=True)
        if preloaded is None:  # the app's own: its worker processes, if any, stop with it
            engine.close()

    return lifespan


def model_executor(torch_threads: int) -> ThreadPoolExecutor:
    # One model thread: the models never run concurrently, batching gives the parallelism.
    return ThreadPoolExecutor(
        1, "ds3d-model", initializer=torch.set_num_threads, initargs=(torch_threads,)
    )


def start_batchers(
    engine: Engine, executor: ThreadPoolExecutor, settings: Settings, metrics: Metrics
) -> Runtime:
    """A running batcher per model queue; no pose queue when the engine has no 2D stage."""

    def start(name: str, run_batch, batch_size: int, queue: int) -> MicroBatcher:
        batcher = MicroBatcher(
            run_batch,
            executor=executor,
            max_batch_size=batch_size,
            max_wait_s=settings.max_wait_ms / 1000.0,
            max_queue=queue,
            max_queue_per_caller=max(1, int(settings.caller_queue_share * queue)),
            on_batch=metrics.batch_observer(name),
        )
        metrics.queue_depth.labels(name).set_function(lambda: batcher.depth)
        batcher.start()
        return batcher

    lift = start("lift", engine.lift_batch, settings.max_lift_batch_size, settings.max_lift_queue)
    pose = None
    if engine.pipeline is not None:
        pose = start("pose", engine.pose_batch, settings.max_batch_size, settings.max_queue)
    if pose is None:
        log.warning("/v1/pose disabled: %s", engine.pose_unavailable)
    return Runtime(engine, lift, pose)


def request_head_bytes(scope: Scope) -> int:
    """Bytes of the request head as sent: the request line and the header lines."""
    target = len(scope["raw_path"]) + (
        len(scope["query_string"]) + 1 if scope["query_string"] else 0
    )
    line = len(scope["method"]) + target + len(" HTTP/1.1\r\n") + 1
    return line + sum(len(k) + len(v) + 4 for k, v in scope["headers"]) + 2


class RefuseLargeHead(HttpMiddleware):
    """Middleware: 431 naming max_header_bytes for a request head over it. (Uvicorn's own parser
    stops reading at 4 times the setting, with a bare 400, so that a huge head is never
    buffered whole.)"""

    async def http(self, scope: Scope, receive: Receive, send: Send) -> None:
        limit = scope["app"].state.settings.max_header_bytes
        if (size := request_head_bytes(scope)) > limit:
            message = f"the request head is {size} bytes, over max_header_bytes = {limit}"
            answer = error_response(ApiError(431, "headers_too_large", message))
            await answer(scope, receive, send)
            return
        await self.app(scope, receive, send)


class ObserveRequests(HttpMiddleware):
    """Middleware: count and time every request by its route template ("unmatched" when no route
    took it), so that the metrics' labels stay few whatever the URLs; a bug is answered 500 (and
    logged), counted like any other answer."""

    async def http(self, scope: Scope, receive: Receive, send: Send) -> None:
        state = scope["app"].state
        t0 = time.perf_counter()
        status: int | None = None

        async def send_observed(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_observed)
        except Exception as exc:
            if status is not None:  # the answer has begun: the server closes the connection
                raise
            answer = error_response(to_api_error(exc, state.settings.retry_after_s))
            await answer(scope, receive, send_observed)
        finally:
            route = scope.get("route")
            label = route.path if route is not None else "unmatched"
            state.metrics.observe_request(label, status or 500, time.perf_counter() - t0)
