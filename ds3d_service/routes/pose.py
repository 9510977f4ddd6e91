"""POST /v1/pose: an image in, the 2D and 3D poses of its people out, through the pose batcher."""

from __future__ import annotations

import time
from typing import Literal

from fastapi import APIRouter, Query, Request

from ds3d.fit.camera import ASSUMED_FOV_DEG
from ds3d.inputs import MAX_COORDINATE_PX, MIN_FOCAL_PX, MIN_SCORE
from ds3d.skeleton import JOINT_NAMES
from ds3d_service.deps import CallerDep, RuntimeHandleDep, SettingsDep
from ds3d_service.engine import request_timings_ms
from ds3d_service.errors import ApiError
from ds3d_service.schemas import ERROR_RESPONSES, PeopleResponse, Person, PoseResponse
from ds3d_service.uploads import POSE_OPENAPI, read_pose_input

router = APIRouter()


@router.post(
    "/v1/pose",
    response_model=PoseResponse | PeopleResponse,
    responses=ERROR_RESPONSES,
    openapi_extra=POSE_OPENAPI,
)
async def pose(
    request: Request,
    settings: SettingsDep,
    runtime: RuntimeHandleDep,
    caller: CallerDep,
    people: Literal["best", "all"] = Query(
        "best", description="best: the likeliest person, as one pose; all: every person found"
    ),
    min_score: float = Query(
        MIN_SCORE, ge=0.0, le=1.0, description="people scoring less are not answered"
    ),
    angles: bool = Query(
        False, description="also each person's joint angles for animation tools (`angles`)"
    ),
    focal_px: float | None = Query(
        None,
        ge=MIN_FOCAL_PX,
        le=MAX_COORDINATE_PX,
        description="without intrinsics, the focal length in pixels of the camera that took the"
        " image, which places the people in its coordinates (root_position); without it a"
        f" camera of a {ASSUMED_FOV_DEG:g}-degree field of view across the longer side is"
        " assumed",
    ),
) -> PoseResponse | PeopleResponse:
    """2D and 3D poses of the people in one image: multipart field `image`, or the raw image
    as the body with an image/* content type; `bbox` and `intrinsics` as JSON (query parameters
    or form fields). Without a bbox the image is searched for people
    of any size. The image is checked (size, header, decoding) before the model is consulted,
    so a bad image is reported whatever the deployment."""
    t0 = time.perf_counter()
    options = {"focal_px": focal_px, "people": people, "min_score": min_score}
    item = await read_pose_input(request, settings, **options)
    rt = runtime.require()
    if rt.pose is None:
        raise ApiError(503, "model_unavailable", rt.engine.pose_unavailable or "no 2D stage")
    out = await rt.pose.submit(item, settings.request_timeout_s, caller)
    common = {
        "joint_names": list(JOINT_NAMES),
        "model": rt.engine.model_id,
        "timings_ms": request_timings_ms([out], time.perf_counter() - t0),
    }
    if people == "all":
        return PeopleResponse(people=[Person.of(p, angles) for p in out.people], **common)
    (best,) = out.people
    answer = Person.of(best, angles).model_dump()
    return PoseResponse(**answer, person_found=best.person_found, **common)
