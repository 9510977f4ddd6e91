"""The dependencies routes declare (FastAPI `Depends`): the app's settings, its metrics and its
loaded models, each read from `request.app.state`, where `create_app` and its lifespan put them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Protocol, TypeVar

from fastapi import Depends, Request
from starlette.datastructures import State

from ds3d.inputs import ImageInput, PoseInput
from ds3d_service.engine import Engine, LiftOutput, PoseOutput
from ds3d_service.errors import ApiError
from ds3d_service.metrics import Metrics
from ds3d_service.settings import Settings

T = TypeVar("T", contravariant=True)
R = TypeVar("R")  # invariant: submit_many answers a list[R]


class ModelQueue(Protocol[T, R]):
    """A model queue as the routes, the health checks and the lifespans use it (and all they
    know of it): ds3d_service.microbatch.MicroBatcher in the plain service,
    ds3d_service.ray_serve.ServeQueue on Ray Serve. submit and submit_many raise
    ds3d_service.microbatch.QueueError's kinds, admitting a request by
    ds3d_service.microbatch.admit."""

    @property
    def depth(self) -> int: ...
    @property
    def saturated(self) -> bool: ...
    @property
    def running(self) -> bool: ...
    @property
    def closing(self) -> bool: ...
    @property
    def stalled_s(self) -> float: ...
    async def submit(self, item: T, timeout_s: float, caller: str = "") -> R: ...
    async def submit_many(
        self, items: Sequence[T], timeout_s: float, caller: str = ""
    ) -> list[R]: ...
    async def close(self, drain_timeout_s: float) -> None: ...


@dataclass
class Runtime:
    """What the lifespan loads: the engine and one queue per model route."""

    engine: Engine
    lift: ModelQueue[PoseInput, LiftOutput]
    pose: ModelQueue[ImageInput, PoseOutput] | None


class RuntimeHandle:
    """The app's Runtime as a route sees it. Routes call `require()` at the point where they need
    the models, after checking their input, so that a bad request gets its own answer even
    while the models are loading (or were never loaded, as in an app run without lifespan)."""

    def __init__(self, state: State):
        self._state = state

    def loaded(self) -> Runtime | None:
        """The loaded Runtime, or None while there is none."""
        return getattr(self._state, "runtime", None)

    def require(self) -> Runtime:
        """The loaded Runtime, or ApiError 503 not_ready (with Retry-After) while there is none."""
        runtime = self.loaded()
        if runtime is None:
            retry_after = {"Retry-After": str(self._state.settings.retry_after_s)}
            raise ApiError(503, "not_ready", "the model is loading", retry_after)
        return runtime


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def get_runtime_handle(request: Request) -> RuntimeHandle:
    return RuntimeHandle(request.app.state)


async def get_caller(request: Request) -> str:
    """Who calls: `key:ID` or `ip:ADDRESS`, as ds3d_service.access.rules.guard found it."""
    return request.state.caller


SettingsDep = Annotated[Settings, Depends(get_settings)]
CallerDep = Annotated[str, Depends(get_caller)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
RuntimeHandleDep = Annotated[RuntimeHandle, Depends(get_runtime_handle)]
