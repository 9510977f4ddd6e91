"""The FastAPI app: routes, request decoding, and the wiring of settings, engine, batchers and
metrics. `create_app(settings)` builds one; the models load in its lifespan (startup)."""

from __future__ import annotations

import asyncio
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from fastapi import Depends, FastAPI, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST
from starlette.datastructures import UploadFile

from ds3d.image_io import decode_image
from ds3d.skeleton import JOINT_NAMES, NUM_JOINTS
from service.batching import MicroBatcher
from service.engine import Engine, LiftInput, LiftOutput, PoseInput, PoseOutput
from service.errors import ApiError, error_response, install_handlers, to_api_error
from service.metrics import Metrics
from service.schemas import (
    ErrorResponse,
    Health,
    LiftRequest,
    LiftResponse,
    LiftResult,
    PoseResponse,
)
from service.settings import Settings

log = logging.getLogger("service")

# Room for the multipart envelope and the small form fields around the image.
MULTIPART_OVERHEAD_BYTES = 64 * 1024

ERROR_RESPONSES = {
    status: {"model": ErrorResponse, "description": what}
    for status, what in {
        413: "body or image over the size limit",
        415: "unsupported content type",
        422: "invalid input (malformed JSON, wrong joint count, non-finite numbers, bad image)",
        503: "queue full, shutting down, or model unavailable (see Retry-After)",
        504: "not answered before the request deadline",
    }.items()
}

POSE_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["image"],
                    "properties": {
                        "image": {"type": "string", "format": "binary"},
                        "bbox": {"type": "string", "description": "JSON [x0, y0, x1, y1] px"},
                        "intrinsics": {"type": "string", "description": "JSON 3x3 matrix"},
                    },
                }
            },
            "image/*": {"schema": {"type": "string", "format": "binary"}},
        },
    }
}


@dataclass
class Runtime:
    """What the lifespan loads: the engine and one batcher per model queue."""

    engine: Engine
    lift: MicroBatcher[LiftInput, LiftOutput]
    pose: MicroBatcher[PoseInput, PoseOutput] | None


def _require_json(request: Request) -> None:
    ctype = request.headers.get("content-type", "")
    if ctype.split(";")[0].strip().lower() != "application/json":
        raise ApiError(415, "unsupported_media_type", "send the body as application/json")


def _parse_array(text: str | None, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    """A JSON array form field or query parameter -> float32 array of `shape`, or None."""
    if text is None or text == "":
        return None
    try:
        arr = np.asarray(json.loads(text), dtype=np.float32)
    except (ValueError, TypeError) as e:
        raise ApiError(422, "invalid_request", f"{name}: not a JSON array of numbers") from e
    if arr.shape != shape or not np.isfinite(arr).all():
        raise ApiError(422, "invalid_request", f"{name}: need finite numbers of shape {shape}")
    return arr


def _check_image_type(ctype: str) -> None:
    if not ctype.startswith("image/"):
        hint = "send the image as multipart field 'image' or a raw image/* body"
        raise ApiError(415, "unsupported_media_type", hint)


async def _read_capped(request: Request, limit: int) -> bytes:
    """The raw body, refused with 413 as soon as it passes `limit` bytes."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise ApiError(413, "payload_too_large", f"the image is over {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _lift_inputs(body: LiftRequest) -> list[LiftInput]:
    items = []
    for i, item in enumerate(body.items):
        with np.errstate(over="ignore"):  # overflow is caught by the check below
            joints = np.asarray(item.joints_2d, dtype=np.float32)
            k = None if item.intrinsics is None else np.asarray(item.intrinsics, dtype=np.float32)
        # Finite doubles can overflow float32 (1e39): check after the cast.
        if not np.isfinite(joints).all() or (k is not None and not np.isfinite(k).all()):
            raise ApiError(422, "invalid_pose", f"items[{i}]: numbers out of float32 range")
        visible = (
            np.ones(NUM_JOINTS, dtype=bool)
            if item.visible is None
            else np.asarray(item.visible, dtype=bool)
        )
        items.append(LiftInput(joints, visible, k))
    return items


def _stage_times(outputs, total_s: float) -> dict[str, float]:
    """Per-stage ms summed over the distinct library calls the outputs ran in, plus the total."""
    stages: dict[str, float] = {}
    for info in {o.batch.call_id: o.batch for o in outputs}.values():
        for stage, ms in info.timings_ms.items():
            stages[stage] = stages.get(stage, 0.0) + ms
    stages["total"] = total_s * 1000.0
    return stages


def create_app(settings: Settings | None = None, engine: Engine | None = None) -> FastAPI:
    """The app for `settings` (default: from the environment). `engine`: already loaded models
    to serve instead of loading settings.model_dir at startup (several apps may share one)."""
    preloaded = engine
    settings = settings or Settings()
    metrics = Metrics()
    timeout = settings.request_timeout_s
    retry_after = {"Retry-After": str(settings.retry_after_s)}

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        torch.set_num_threads(settings.torch_threads)
        # One model thread: the models never run concurrently, batching gives the parallelism.
        executor = ThreadPoolExecutor(
            1, "ds3d-model", initializer=torch.set_num_threads, initargs=(settings.torch_threads,)
        )
        loop = asyncio.get_running_loop()
        engine = preloaded or await loop.run_in_executor(
            executor, partial(Engine.load, settings.model_dir, settings.device)
        )
        engine.on_timings = metrics.observe_stages

        def batcher(name, fn):
            b = MicroBatcher(
                fn,
                executor=executor,
                max_batch_size=settings.max_batch_size,
                max_wait_s=settings.max_wait_ms / 1000.0,
                max_queue=settings.max_queue,
                on_batch=metrics.batch_observer(name),
            )
            metrics.queue_depth.labels(name).set_function(lambda: b.depth)
            b.start()
            return b

        lift = batcher("lift", engine.lift_batch)
        pose = batcher("pose", engine.pose_batch) if engine.pipeline is not None else None
        if pose is None:
            log.warning("/v1/pose disabled: %s", engine.pose_unavailable)
        app.state.runtime = Runtime(engine, lift, pose)
        log.info("model %s loaded; serving", engine.model_id)
        yield
        # Uvicorn has stopped taking requests; finish what is queued, then stop.
        for b in (lift, pose):
            if b is not None:
                await b.close(drain_timeout_s=timeout)
        executor.shutdown(wait=True)

    app = FastAPI(
        title="ds3d",
        version="0.1.0",
        description="3D human pose from a single image (dual-source approach, Yasin et al. "
        "CVPR 2016). 2D joints in pixels, 3D joints in millimetres, 14 joints in LSP order.",
        lifespan=lifespan,
    )
    install_handlers(app, settings.retry_after_s)

    @app.middleware("http")
    async def observe(request: Request, call_next):
        t0 = time.perf_counter()
        try:
            response = await call_next(request)
        except Exception as exc:  # a bug: answer 500 (and log it), counted like any other
            response = error_response(to_api_error(exc, settings.retry_after_s))
        route = request.scope.get("route")
        label = route.path if route is not None else "unmatched"
        metrics.observe_request(label, response.status_code, time.perf_counter() - t0)
        return response

    def runtime(request: Request) -> Runtime:
        rt = getattr(request.app.state, "runtime", None)
        if rt is None:
            raise ApiError(503, "not_ready", "the model is loading", retry_after)
        return rt

    @app.post(
        "/v1/lift",
        response_model=LiftResponse,
        responses=ERROR_RESPONSES,
        dependencies=[Depends(_require_json)],
    )
    async def lift(body: LiftRequest, request: Request) -> LiftResponse:
        """Lift 2D poses (pixels) to 3D (millimetres). Items are answered in order; each is one
        element of a model batch shared with other requests."""
        t0 = time.perf_counter()
        rt = runtime(request)
        # A request larger than the whole queue could never be taken: 413, not a 503 to retry.
        most = min(settings.max_lift_items, settings.max_queue)
        if len(body.items) > most:
            why = f"{len(body.items)} items, at most {most}"
            raise ApiError(413, "too_many_items", why)
        outputs = await rt.lift.submit_many(_lift_inputs(body), timeout)
        return LiftResponse(
            items=[
                LiftResult(joints_3d=o.joints_3d.tolist(), joint_set=o.joint_set, energy=o.energy)
                for o in outputs
            ],
            joint_names=list(JOINT_NAMES),
            model=rt.engine.model_id,
            timings_ms=_stage_times(outputs, time.perf_counter() - t0),
        )

    @app.post(
        "/v1/pose", response_model=PoseResponse, responses=ERROR_RESPONSES, openapi_extra=POSE_BODY
    )
    async def pose(
        request: Request,
        bbox: str | None = Query(None, description="JSON [x0, y0, x1, y1] pixels"),
        intrinsics: str | None = Query(None, description="JSON 3x3 camera matrix"),
    ) -> PoseResponse:
        """2D and 3D pose of the person in one image: multipart field `image`, or the raw image
        as the body with an image/* content type. The image is checked (size, header, decoding)
        before the model is consulted, so a bad image is reported whatever the deployment."""
        t0 = time.perf_counter()
        limit = settings.max_image_bytes
        ctype = request.headers.get("content-type", "").lower()
        length = request.headers.get("content-length")
        if length and length.isdigit() and int(length) > limit + MULTIPART_OVERHEAD_BYTES:
            raise ApiError(413, "payload_too_large", f"the body is over {limit} bytes")
        if ctype.startswith("multipart/form-data"):
            form = await request.form(max_files=1, max_fields=8)
            upload = form.get("image")
            if not isinstance(upload, UploadFile):
                raise ApiError(422, "invalid_request", "multipart field 'image' (a file) missing")
            if upload.size is not None and upload.size > limit:
                raise ApiError(413, "payload_too_large", f"the image is over {limit} bytes")
            data = await upload.read()
            bbox = form.get("bbox") if isinstance(form.get("bbox"), str) else bbox
            intrinsics = (
                form.get("intrinsics") if isinstance(form.get("intrinsics"), str) else intrinsics
            )
        else:
            _check_image_type(ctype)
            data = await _read_capped(request, limit)
        box = _parse_array(bbox, (4,), "bbox")
        k = _parse_array(intrinsics, (3, 3), "intrinsics")
        image = await run_in_threadpool(decode_image, data, settings.max_image_pixels)
        rt = runtime(request)
        if rt.pose is None:
            raise ApiError(503, "model_unavailable", rt.engine.pose_unavailable or "no 2D stage")
        out = await rt.pose.submit(PoseInput(image, box, k), timeout)
        return PoseResponse(
            joint_names=list(JOINT_NAMES),
            joints_2d=out.joints_2d.tolist(),
            joints_3d=out.joints_3d.tolist(),
            confidence=out.confidence.tolist(),
            facing_camera=out.facing_camera,
            joint_set=out.joint_set,
            model=rt.engine.model_id,
            timings_ms=_stage_times([out], time.perf_counter() - t0),
        )

    @app.get("/healthz", response_model=Health)
    async def healthz() -> Health:
        """Alive: the process answers."""
        return Health(status="alive")

    @app.get("/readyz", response_model=Health, responses={503: {"model": ErrorResponse}})
    async def readyz(request: Request):
        """Ready: the model is loaded, the batch worker runs, and the queue is not full."""
        rt = runtime(request)
        if not rt.lift.running:
            raise ApiError(503, "not_ready", "the batch worker is not running")
        if rt.lift.saturated:
            raise ApiError(503, "saturated", "the queue is full", retry_after)
        return JSONResponse(
            Health(
                status="ready",
                model=rt.engine.model_id,
                queue_depth=rt.lift.depth,
                pose_available=rt.pose is not None,
            ).model_dump()
        )

    @app.get("/metrics", include_in_schema=False)
    async def prometheus() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    return app
