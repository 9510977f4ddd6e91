"""POST /v1/pose: an image in, the 2D and 3D pose of its person out, through the pose batcher."""

from __future__ import annotations

import time

from fastapi import APIRouter, Query, Request

from ds3d.skeleton import JOINT_NAMES
from service.deps import RuntimeHandleDep, SettingsDep
from service.engine import request_timings_ms
from service.errors import ApiError
from service.schemas import ERROR_RESPONSES, PoseResponse
from service.uploads import POSE_BODY, read_pose_input

router = APIRouter()


@router.post(
    "/v1/pose", response_model=PoseResponse, responses=ERROR_RESPONSES, openapi_extra=POSE_BODY
)
async def pose(
    request: Request,
    settings: SettingsDep,
    runtime: RuntimeHandleDep,
    bbox: str | None = Query(None, description="JSON [x0, y0, x1, y1] pixels"),
    intrinsics: str | None = Query(None, description="JSON 3x3 camera matrix"),
) -> PoseResponse:
    """2D and 3D pose of the person in one image: multipart field `image`, or the raw image
    as the body with an image/* content type. The image is checked (size, header, decoding)
    before the model is consulted, so a bad image is reported whatever the deployment."""
    t0 = time.perf_counter()
    item = await read_pose_input(request, settings, bbox, intrinsics)
    rt = runtime.require()
    if rt.pose is None:
        raise ApiError(503, "model_unavailable", rt.engine.pose_unavailable or "no 2D stage")
    out = await rt.pose.submit(item, settings.request_timeout_s)
    return PoseResponse(
        joint_names=list(JOINT_NAMES),
        joints_2d=out.joints_2d.tolist(),
        joints_3d=out.joints_3d.tolist(),
        confidence=out.confidence.tolist(),
        facing_camera=out.facing_camera,
        joint_set=out.joint_set,
        model=rt.engine.model_id,
        timings_ms=request_timings_ms([out], time.perf_counter() - t0),
    )
