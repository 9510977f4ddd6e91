"""The operator's routes: /healthz (alive: restart it when not), /readyz (able to take work: send
it none when not) and /metrics (Prometheus text)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST

from ds3d_service.deps import MetricsDep, ModelQueue, Runtime, RuntimeHandleDep, SettingsDep
from ds3d_service.errors import ApiError
from ds3d_service.schemas import ErrorResponse, Health
from ds3d_service.settings import Settings

router = APIRouter()


@router.get("/healthz", response_model=Health, responses={503: {"model": ErrorResponse}})
async def healthz(settings: SettingsDep, runtime: RuntimeHandleDep):
    """Alive: the process answers, and once the models are loaded, every batch worker runs and
    none has held work without finishing a batch for live_stall_s (503: restart it)."""
    rt = runtime.loaded()
    if rt is not None:
        for name, queue in queues(rt):
            if not queue.running and not queue.closing:
                raise ApiError(503, "dead", f"the {name} batch worker has stopped")
            if queue.stalled_s > settings.live_stall_s:
                raise ApiError(503, "stalled", stalled(name, queue, "live_stall_s", settings))
    return Health(status="alive")


@router.get("/readyz", response_model=Health, responses={503: {"model": ErrorResponse}})
async def readyz(settings: SettingsDep, runtime: RuntimeHandleDep):
    """Ready: the models are loaded, every batch worker runs and keeps up (none has held work
    without finishing a batch for ready_stall_s), and the lift queue is not full."""
    rt = runtime.require()
    for name, queue in queues(rt):
        if not queue.running:
            raise ApiError(503, "not_ready", f"the {name} batch worker is not running")
        if queue.stalled_s > settings.ready_stall_s:
            raise ApiError(503, "stalled", stalled(name, queue, "ready_stall_s", settings))
    if rt.lift.saturated:
        retry_after = {"Retry-After": str(settings.retry_after_s)}
        raise ApiError(503, "saturated", "the queue is full", retry_after)
    return JSONResponse(
        Health(
            status="ready",
            model=rt.engine.model_id,
            queue_depth=rt.lift.depth,
            pose_available=rt.pose is not None,
        ).model_dump()
    )


def queues(rt: Runtime) -> list[tuple[str, ModelQueue]]:
    return [("lift", rt.lift)] + ([("pose", rt.pose)] if rt.pose is not None else [])


def stalled(name: str, queue: ModelQueue, setting: str, settings: Settings) -> str:
    return (
        f"the {name} batch worker has held work for {queue.stalled_s:.0f} s without finishing "
        f"a batch, over {setting} = {getattr(settings, setting):g}"
    )


@router.get("/metrics", include_in_schema=False)
async def prometheus(metrics: MetricsDep) -> Response:
    return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)
