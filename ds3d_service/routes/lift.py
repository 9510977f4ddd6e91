"""POST /v1/lift: 2D poses (pixels) in, 3D poses (millimetres) out, through the lift batcher."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends, Request

from ds3d.errors import InvalidPose
from ds3d.inputs import PoseInput, pose_input
from ds3d.skeleton import BONE_NAMES, JOINT_NAMES
from ds3d_service.deps import CallerDep, RuntimeHandleDep, SettingsDep
from ds3d_service.engine import request_timings_ms
from ds3d_service.errors import ApiError
from ds3d_service.schemas import ERROR_RESPONSES, LiftedPose, LiftRequest, LiftResponse

router = APIRouter()


def require_json(request: Request) -> None:
    ctype = request.headers.get("content-type", "")
    if ctype.split(";")[0].strip().lower() != "application/json":
        raise ApiError(415, "unsupported_media_type", "send the body as application/json")


def lift_inputs(body: LiftRequest) -> list[PoseInput]:
    """The batcher's items of a validated request, each checked by the library (ds3d.inputs.
    pose_input): 422 naming the item it refuses."""
    items = []
    for i, item in enumerate(body.items):
        try:
            items.append(pose_input(item.joints_2d, item.visible, item.intrinsics))
        except InvalidPose as exc:
            raise ApiError(422, "invalid_pose", f"items[{i}]: {exc}") from exc
    return items


@router.post(
    "/v1/lift",
    response_model=LiftResponse,
    responses=ERROR_RESPONSES,
    dependencies=[Depends(require_json)],
)
async def lift(
    body: LiftRequest, settings: SettingsDep, runtime: RuntimeHandleDep, caller: CallerDep
) -> LiftResponse:
    """Lift 2D poses (pixels) to 3D (millimetres). Items are answered in order; each is one
    element of a model batch shared with other requests."""
    t0 = time.perf_counter()
    rt = runtime.require()
    # A request larger than the whole queue could never be taken: 413, not a 503 to retry.
    name, most = min(
        ("max_lift_items", settings.max_lift_items),
        ("max_lift_queue", settings.max_lift_queue),
        key=lambda limit: limit[1],
    )
    if len(body.items) > most:
        why = f"{len(body.items)} items, over {name} = {most}"
        raise ApiError(413, "too_many_items", why)
    items = lift_inputs(body)
    outputs = await rt.lift.submit_many(items, settings.request_timeout_s, caller)
    return LiftResponse(
        items=[LiftedPose.of(o.pose) for o in outputs],
        joint_names=list(JOINT_NAMES),
        bone_names=list(BONE_NAMES),
        model=rt.engine.model_id,
        timings_ms=request_timings_ms(outputs, time.perf_counter() - t0),
    )
