"""POST /v1/lift: 2D poses (pixels) in, 3D poses (millimetres) out, through the lift batcher."""

from __future__ import annotations

import time

import numpy as np
from fastapi import APIRouter, Depends, Request

from ds3d.errors import InvalidPose
from ds3d.skeleton import BONE_NAMES, JOINT_NAMES, NUM_JOINTS
from service.deps import CallerDep, RuntimeHandleDep, SettingsDep
from service.engine import LiftInput, request_timings_ms
from service.errors import ApiError
from service.schemas import ERROR_RESPONSES, LiftRequest, LiftResponse, LiftResult

router = APIRouter()


def require_json(request: Request) -> None:
    ctype = request.headers.get("content-type", "")
    if ctype.split(";")[0].strip().lower() != "application/json":
        raise ApiError(415, "unsupported_media_type", "send the body as application/json")


def lift_inputs(body: LiftRequest) -> list[LiftInput]:
    """The batcher's items of a validated request (its numbers within float32's range: the
    schema bounds them by ds3d.inputs.MAX_COORDINATE_PX)."""
    return [
        LiftInput(
            np.asarray(item.joints_2d, dtype=np.float32),
            np.ones(NUM_JOINTS, bool) if item.visible is None else np.asarray(item.visible, bool),
            None if item.intrinsics is None else np.asarray(item.intrinsics, dtype=np.float32),
        )
        for item in body.items
    ]


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
    for i, item in enumerate(items):
        try:
            rt.engine.check_lift_input(item)
        except InvalidPose as exc:
            raise ApiError(422, "invalid_pose", f"items[{i}]: {exc}") from exc
    outputs = await rt.lift.submit_many(items, settings.request_timeout_s, caller)
    return LiftResponse(
        items=[
            LiftResult(
                joints_3d=o.joints_3d.tolist(),
                bone_lengths=o.bone_lengths.tolist(),
                joint_set=o.joint_set,
                energy=o.energy,
                root_position=None if o.root_position is None else o.root_position.tolist(),
            )
            for o in outputs
        ],
        joint_names=list(JOINT_NAMES),
        bone_names=list(BONE_NAMES),
        model=rt.engine.model_id,
        timings_ms=request_timings_ms(outputs, time.perf_counter() - t0),
    )
