"""The HTTP API served by Ray Serve: an optional scale-out path (`pip install -e .[ray]`); the
plain service (`ds3d-serve`) stays the default.

    python -m ds3d_service.ray_serve [--min-replicas 1] [--max-replicas 2] [DS3D-SERVE FLAGS]
    serve run docker/ray-serve.yaml          (the same, from a Serve config file)

`python -m ds3d_service.ray_serve` starts a local Ray (or joins `--address`), serves the app on
--host/--port (default 127.0.0.1:8000) and runs until Ctrl-C or SIGTERM. Every `ds3d-serve` flag and
DS3D_* env var applies (`python -m ds3d_service --help`) except those of uvicorn (max_connections)
and torch_threads: each replica is one Ray actor of one CPU running torch on one thread. Replica
bounds and backpressure: --min-replicas, --max-replicas, --target-ongoing-requests, --max-ongoing-
requests, --max-queued-requests (also DS3D_RAY_MIN_REPLICAS, ...). Each replica serves the app of
`ds3d_service.app.create_app` (same routes, JSON errors, access guard, metrics), with a runtime
whose lift and pose queues (`ServeQueue`) are ModelQueues (ds3d_service.deps) as the plain service's
MicroBatchers are, but batch through `@serve.batch` methods (max_lift_batch_size / max_batch_size,
max_wait_ms). A batch the engine refuses is rerun item by item, so one bad item fails only its own
request. Overload answers 503 with Retry-After (retry_after_s) twice over: a replica holding
max_lift_queue / max_queue items answers the service's JSON `overloaded`; past max_ongoing_requests
per replica and max_queued_requests waiting in Ray's proxy, the proxy answers 503 itself, with
Retry-After and a text body (Ray's, not JSON; the SDK retries either). Differences from the plain
service: batches are first come first served (no round robin across callers; caller_queue_share is
still enforced per replica), and each replica keeps its own /metrics and its own rate limits
(rate_limit_rps applies per replica).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import logging
import os
import signal
import sys
import time
from collections.abc import Awaitable, Callable, Sequence
from contextlib import asynccontextmanager
from typing import Any, Generic, TypeVar, cast

import torch
from fastapi import FastAPI
from ray import serve
from ray.serve.config import BackpressureConfig
from starlette.datastructures import MutableHeaders
from starlette.types import Message, Receive, Scope, Send

from ds3d_service.app import create_app, model_executor
from ds3d_service.deps import Runtime
from ds3d_service.engine import Engine
from ds3d_service.microbatch import (
    BatchStats,
    DeadlineExceeded,
    ItemFailed,
    ProgressClock,
    admit,
    first_result,
)
from ds3d_service.middleware import HttpMiddleware
from ds3d_service.settings import Settings

log = logging.getLogger("ds3d_service.ray_serve")

T = TypeVar("T")
R = TypeVar("R")

DEPLOYMENT = "Ds3dServe"
# Replica bounds and backpressure: option name -> (default, help).
SCALING = {
    "min_replicas": (1, "Fewest replicas (one CPU each) the autoscaler keeps."),
    "max_replicas": (2, "Most replicas the autoscaler starts."),
    "target_ongoing_requests": (8, "Requests per replica the autoscaler aims at."),
    "max_ongoing_requests": (64, "Requests one replica takes at once; more wait in the proxy."),
    "max_queued_requests": (64, "Requests waiting in the proxy; past it 503 (-1: no limit)."),
}


class ServeQueue(Generic[T, R]):
    """One model queue of a replica, a ds3d_service.deps.ModelQueue as MicroBatcher is (the same
    admission checks, errors and health figures). Each item is one call of `run_item`, a
    `@serve.batch` method: Ray forms the batches. `run_item` answers an item's output or the
    exception it failed with. (Each request here gives up at its deadline, so stalled_s stays
    below request_timeout_s: a stuck replica is Ray's health check's to find.)"""

    def __init__(
        self,
        run_item: Callable[[T], Awaitable[R | Exception]],
        max_queue: int,
        max_queue_per_caller: int,
    ):
        self._run_item = run_item
        self.max_queue = max_queue
        self.max_queue_per_caller = max_queue_per_caller
        self._depth = 0  # items of this replica not yet answered
        self._per_caller: collections.Counter[str] = collections.Counter()
        self._closing = False
        self._clock = ProgressClock()

    @property
    def depth(self) -> int:
        """Items of this replica not yet answered."""
        return self._depth

    @property
    def saturated(self) -> bool:
        return self._depth >= self.max_queue

    @property
    def running(self) -> bool:
        return not self._closing

    @property
    def closing(self) -> bool:
        return self._closing

    @property
    def stalled_s(self) -> float:
        """Seconds this replica has had items in flight without answering one."""
        return self._clock.stalled_s

    async def submit(self, item: T, timeout_s: float, caller: str = "") -> R:
        return await first_result(self.submit_many([item], timeout_s, caller))

    async def submit_many(self, items: Sequence[T], timeout_s: float, caller: str = "") -> list[R]:
        """As MicroBatcher.submit_many: what `admit` raises, DeadlineExceeded, or ItemFailed for
        the first item that failed."""
        admit(
            len(items),
            closing=self._closing,
            depth=self._depth,
            max_queue=self.max_queue,
            waiting=self._per_caller[caller],
            max_queue_per_caller=self.max_queue_per_caller,
        )
        self._depth += len(items)
        self._per_caller[caller] += len(items)
        self._clock.work_arrived()
        try:
            calls = asyncio.gather(*(self._run_item(item) for item in items))
            outcomes = await asyncio.wait_for(calls, timeout_s)
        except TimeoutError:
            raise DeadlineExceeded(f"not answered within {timeout_s:g} s") from None
        finally:
            self._depth -= len(items)
            self._clock.progressed(more_work=self._depth > 0)
            self._per_caller[caller] -= len(items)
            if not self._per_caller[caller]:
                del self._per_caller[caller]
        results: list[R] = []
        for i, outcome in enumerate(outcomes):
            if isinstance(outcome, Exception):
                raise ItemFailed(i, outcome)
            results.append(outcome)
        return results

    async def close(self, drain_timeout_s: float) -> None:
        """Take no new work. What is in flight is Ray Serve's to drain (its graceful shutdown),
        so this returns at once."""
        self._closing = True


class OneRequestId(HttpMiddleware):
    """Middleware: drop the app's X-Request-ID from the answers. Ray's proxy adds its own to
    every answer: the id it passed in (the client's, or a new one), which the access guard took
    as the request's id; without this the header came twice."""

    async def http(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def send_without_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                del MutableHeaders(scope=message)["x-request-id"]
            await send(message)

        await self.app(scope, receive, send_without_id)


@serve.deployment(name=DEPLOYMENT, ray_actor_options={"num_cpus": 1})
@serve.ingress()
class Ds3dServe:
    """One replica: the models on one torch thread and the app of create_app around them."""

    def __init__(self, settings: Settings):
        torch.set_num_threads(1)
        self.settings = settings
        self.engine = Engine.load(settings.model_dir, settings.device)
        self.executor = model_executor(1)  # the one model thread, off the event loop
        wait_s = settings.max_wait_ms / 1000.0
        for batched, size in (
            (self.lift_items, settings.max_lift_batch_size),
            (self.pose_items, settings.max_batch_size),
        ):
            batched.set_max_batch_size(size)
            batched.set_batch_wait_timeout_s(wait_s)

    def __serve_build_asgi_app__(self) -> FastAPI:
        """The replica's app (Ray calls it after __init__, then runs the app's lifespan)."""
        app = create_app(self.settings, self.engine)
        # Not create_app's lifespan, which would start MicroBatchers: queues on @serve.batch.
        app.router.lifespan_context = self._lifespan
        app.add_middleware(OneRequestId)
        return app

    @asynccontextmanager
    async def _lifespan(self, app: FastAPI):
        s = self.settings
        metrics = app.state.metrics
        self.engine.on_timings = metrics.observe_stages
        self.on_batch = {name: metrics.batch_observer(name) for name in ("lift", "pose")}

        def queue(run_item, size: int) -> ServeQueue:
            return ServeQueue(run_item, size, max(1, int(s.caller_queue_share * size)))

        lift = queue(self.lift_items, s.max_lift_queue)
        pose = queue(self.pose_items, s.max_queue) if self.engine.pipeline is not None else None
        for name, q in (("lift", lift), ("pose", pose)):
            if q is not None:
                metrics.queue_depth.labels(name).set_function(lambda q=q: q.depth)
        app.state.runtime = Runtime(self.engine, lift, pose)
        log.info("replica serving model %s", self.engine.model_id)
        yield
        for q in (lift, pose):
            if q is not None:
                await q.close(drain_timeout_s=s.request_timeout_s)
        self.executor.shutdown(wait=True)

    # The batch sizes and waits are set from the settings in __init__.
    @serve.batch(max_batch_size=64, batch_wait_timeout_s=0.005)
    async def lift_items(self, items: list) -> list:
        return await self._run("lift", self.engine.lift_batch, items)

    @serve.batch(max_batch_size=16, batch_wait_timeout_s=0.005)
    async def pose_items(self, items: list) -> list:
        return await self._run("pose", self.engine.pose_batch, items)

    async def _run(self, queue: str, run_batch: Callable[[list], list], items: list) -> list:
        """Outputs of one batch on the model thread; when the batch function raises, the items
        again one by one, each answering its output or its exception (as MicroBatcher)."""
        loop = asyncio.get_running_loop()
        t0 = time.perf_counter()
        try:
            outcomes = list(await loop.run_in_executor(self.executor, run_batch, items))
        except Exception as batch_error:
            outcomes = [batch_error]
            if len(items) > 1:
                outcomes = [await self._run_one(run_batch, item) for item in items]
        self.on_batch[queue](BatchStats(len(items), time.perf_counter() - t0))
        return outcomes

    async def _run_one(self, run_batch: Callable[[list], list], item: Any) -> Any:
        try:
            (output,) = await asyncio.get_running_loop().run_in_executor(
                self.executor, run_batch, [item]
            )
            return output
        except Exception as e:
            return e


def build_app(settings: Settings, **scaling: int) -> serve.Application:
    """The Serve application for `settings`; `scaling`: keys of SCALING (default: theirs)."""
    opts = {name: default for name, (default, _) in SCALING.items()} | scaling
    # The class decorators made Ds3dServe a Deployment, which type checkers do not see.
    deployment = cast(serve.Deployment, Ds3dServe)
    return deployment.options(
        autoscaling_config={
            "min_replicas": opts["min_replicas"],
            "initial_replicas": opts["min_replicas"],
            "max_replicas": opts["max_replicas"],
            "target_ongoing_requests": opts["target_ongoing_requests"],
        },
        max_ongoing_requests=opts["max_ongoing_requests"],
        max_queued_requests=opts["max_queued_requests"],
        backpressure_config=BackpressureConfig(
            status_code=503, retry_after_s=settings.retry_after_s
        ),
    ).bind(settings)


def app_builder(args: dict[str, Any]) -> serve.Application:
    """`serve run` / a Serve config's import_path: `args` holds SCALING keys and Settings fields
    (over the DS3D_* env vars)."""
    args = dict(args)
    scaling = {name: int(args.pop(name)) for name in SCALING if name in args}
    return build_app(Settings(**args), **scaling)


def http_options(settings: Settings) -> dict[str, Any]:
    return {
        "host": settings.host,
        "port": settings.port,
        "keep_alive_timeout_s": settings.keep_alive_s,
    }


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, Settings]:
    """Ray's own flags, then the ds3d-serve flags (ds3d_service/__main__.py) from the rest."""
    from ds3d_service.__main__ import parse_settings

    parser = argparse.ArgumentParser(
        prog="python -m ds3d_service.ray_serve",
        description="Serve the ds3d HTTP API with Ray Serve: replicas of one CPU and one torch "
        "thread, autoscaled between the bounds below.",
        epilog="Every ds3d-serve flag and DS3D_* env var applies too "
        "(python -m ds3d_service --help), "
        "but torch_threads (1 per replica) and uvicorn's own (max_connections).",
    )
    parser.add_argument("--address", help="Ray cluster to join (default: start a local one)")
    for name, (default, help_) in SCALING.items():
        env = f"DS3D_RAY_{name.upper()}"
        parser.add_argument(
            "--" + name.replace("_", "-"),
            type=int,
            default=int(os.environ.get(env, default)),
            help=f"{help_} Env {env}; default {default}.",
        )
    opts, rest = parser.parse_known_args(argv)
    return opts, parse_settings(rest)


def main(argv: list[str] | None = None) -> int:
    import ray

    opts, settings = parse_args(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(name)s %(message)s")
    scaling = {name: getattr(opts, name) for name in SCALING}
    ray.init(address=opts.address, include_dashboard=False)
    serve.start(http_options=http_options(settings))
    serve.run(build_app(settings, **scaling), name="ds3d", route_prefix="/")
    log.info("serving on http://%s:%d (%s)", settings.host, settings.port, scaling)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        serve.shutdown()
        ray.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
