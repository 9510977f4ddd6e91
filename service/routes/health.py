"""The operator's routes: /healthz (alive), /readyz (able to take work) and /metrics
(Prometheus text)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST

from service.deps import MetricsDep, RuntimeHandleDep, SettingsDep
from service.errors import ApiError
from service.schemas import ErrorResponse, Health

router = APIRouter()


@router.get("/healthz", response_model=Health)
async def healthz() -> Health:
    """Alive: the process answers."""
    return Health(status="alive")


@router.get("/readyz", response_model=Health, responses={503: {"model": ErrorResponse}})
async def readyz(settings: SettingsDep, runtime: RuntimeHandleDep):
    """Ready: the model is loaded, the batch worker runs, and the queue is not full."""
    rt = runtime.require()
    if not rt.lift.running:
        raise ApiError(503, "not_ready", "the batch worker is not running")
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


@router.get("/metrics", include_in_schema=False)
async def prometheus(metrics: MetricsDep) -> Response:
    return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)
