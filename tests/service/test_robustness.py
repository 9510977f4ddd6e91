"""Inputs and failures that must not take the service down: every one is answered in bounded
time (a 422 naming the limit, or a normal answer), a failing batch fails only its own requests,
and the health checks tell a stuck model worker."""

from __future__ import annotations

import io
import threading
import time

import httpx
import numpy as np
import pytest
from PIL import Image

from ds3d.data.lsp import load_lsp
from ds3d.inputs import MAX_ASPECT_RATIO
from ds3d_service.engine import Engine

# Degenerate but schema-valid 2D poses for /v1/lift: (joints_2d, visible, intrinsics).
RNG = np.random.default_rng(0)
SPREAD = RNG.uniform(0, 300, (14, 2)).tolist()
CAMERA = [[500.0, 0.0, 150.0], [0.0, 500.0, 150.0], [0.0, 0.0, 1.0]]
DEGENERATE_POSES = {
    "all joints at one point": ([[100.0, 200.0]] * 14, None, None),
    "at one point, with a camera": ([[100.0, 200.0]] * 14, None, CAMERA),
    "coordinates of 1e30": ([[1e30, -1e30]] * 7 + [[-1e30, 1e30]] * 7, None, None),
    "singular intrinsics": (SPREAD, None, [[500.0, 0, 150], [0, 500.0, 150], [0, 0, 0]]),
    "zero intrinsics": (SPREAD, None, [[0.0] * 3] * 3),
    "a focal length of 1e30": (SPREAD, None, [[1e30, 0, 150], [0, 1e30, 150], [0, 0, 1]]),
    "no joint visible": (SPREAD, [False] * 14, None),
    "one joint visible": (SPREAD, [True] + [False] * 13, None),
}


def png(height: int, width: int) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), (90, 120, 60)).save(buffer, "PNG")
    return buffer.getvalue()


def post_image(url: str, data: bytes, timeout: float = 60, **params) -> httpx.Response:
    return httpx.post(
        f"{url}/v1/pose", params=params, content=data, headers={"content-type": "image/png"},
        timeout=timeout,
    )  # fmt: skip


def timed(call):
    t0 = time.perf_counter()
    response = call()
    return response, time.perf_counter() - t0


@pytest.fixture(scope="module")
def photo(data_dir) -> bytes:
    return load_lsp(split="test").image_paths[0].read_bytes()


def test_a_thin_strip_is_refused_at_once_and_the_service_serves_on(pose_engine, serving, photo):
    limit = MAX_ASPECT_RATIO
    with serving(pose_engine, request_timeout_s=30) as u:
        strip, seconds = timed(lambda: post_image(u, png(8, 8000)))
        assert strip.status_code == 422 and seconds < 5, (strip.text, seconds)
        assert strip.json()["error"]["code"] == "invalid_image"
        assert "max_aspect_ratio" in strip.json()["error"]["message"]
        tall = post_image(u, png(8000, 8))
        assert tall.status_code == 422
        # The same strip with a box needs no search: an answer, in bounded time.
        boxed, seconds = timed(lambda: post_image(u, png(8, 8000), bbox="[100, 0, 108, 8]"))
        assert boxed.status_code == 200 and seconds < 10, (boxed.text, seconds)
        # As elongated as the search takes: an answer (nobody in a flat colour).
        wide = post_image(u, png(100, int(100 * limit)))
        assert wide.status_code == 200, wide.text
        answer, seconds = timed(
            lambda: httpx.post(
                f"{u}/v1/pose", content=photo, headers={"content-type": "image/jpeg"}, timeout=60
            )
        )
        assert answer.status_code == 200 and seconds < 10, (answer.text, seconds)
        assert httpx.get(f"{u}/readyz").status_code == 200


@pytest.mark.parametrize(
    "intrinsics",
    [
        "[[0,0,0],[0,0,0],[0,0,0]]",
        "[[-500,0,100],[0,-500,100],[0,0,1]]",
        "[[500,0,1],[0,0,1],[0,0,1]]",
    ],
    ids=["all zero", "negative focal", "zero fy"],
)
def test_degenerate_intrinsics_on_pose_are_refused_at_once(pose_engine, serving, photo, intrinsics):
    with serving(pose_engine) as u:
        params = {"intrinsics": intrinsics}
        refused, seconds = timed(lambda: post_image(u, photo, timeout=30, **params))
        assert refused.status_code == 422 and seconds < 1, (refused.text, seconds)
        assert refused.json()["error"]["message"].startswith("intrinsics")
        assert httpx.get(f"{u}/healthz").status_code == 200
        assert httpx.get(f"{u}/readyz").status_code == 200


@pytest.mark.parametrize("case", DEGENERATE_POSES, ids=list(DEGENERATE_POSES))
def test_degenerate_poses_on_lift_are_answered_within_a_second(engine, serving, case):
    joints, visible, intrinsics = DEGENERATE_POSES[case]
    item = {"joints_2d": joints}
    if visible is not None:
        item["visible"] = visible
    if intrinsics is not None:
        item["intrinsics"] = intrinsics
    good = {"joints_2d": SPREAD}
    with serving(engine) as u:
        httpx.post(f"{u}/v1/lift", json={"items": [good]}, timeout=30)  # warm
        response, seconds = timed(
            lambda: httpx.post(f"{u}/v1/lift", json={"items": [item]}, timeout=30)
        )
        assert response.status_code in (200, 422) and seconds < 1, (response.text, seconds)
        if response.status_code == 200:
            (answer,) = response.json()["items"]
            assert np.isfinite(answer["joints_3d"]).all() and np.isfinite(answer["energy"])
        else:
            assert response.json()["error"]["code"] in ("invalid_request", "invalid_pose")
        assert httpx.get(f"{u}/healthz").status_code == 200
        after = httpx.post(f"{u}/v1/lift", json={"items": [good]}, timeout=30)
        assert after.status_code == 200


class Interrupted(BaseException):
    """Not an Exception: what a library calling sys.exit or a stray KeyboardInterrupt raises."""


class FailingEngine(Engine):
    """The bundled engine, whose lift batches fail when a pose's first x is `fail_at`, and
    block until `release` is set when it is `block_at`."""

    def __init__(self, engine: Engine, fail_at: float, block_at: float):
        super().__init__(engine.lifter, engine.pipeline, engine.pose_unavailable)
        self.fail_at, self.block_at = fail_at, block_at
        self.release = threading.Event()

    def lift_batch(self, items):
        firsts = {float(item.joints_2d[0, 0]) for item in items}
        if self.fail_at in firsts:
            raise Interrupted("the batch went wrong")
        if self.block_at in firsts:
            self.release.wait(30)
        return super().lift_batch(items)


def test_a_failing_batch_fails_its_requests_and_the_queue_serves_on(engine, serving):
    failing = FailingEngine(engine, fail_at=7.0, block_at=-1.0)
    bad = {"joints_2d": [[7.0, 0.0], *SPREAD[1:]]}
    with serving(failing) as u:
        for _ in range(2):
            response = httpx.post(f"{u}/v1/lift", json={"items": [bad]}, timeout=30)
            assert response.status_code == 500, response.text
            assert response.json()["error"]["code"] == "internal"
        good = httpx.post(f"{u}/v1/lift", json={"items": [{"joints_2d": SPREAD}]}, timeout=30)
        assert good.status_code == 200, good.text
        # A bad pose in a batch with good ones fails alone.
        both = httpx.post(f"{u}/v1/lift", json={"items": [{"joints_2d": SPREAD}] * 2}, timeout=30)
        assert both.status_code == 200
        assert httpx.get(f"{u}/readyz").status_code == 200
        assert httpx.get(f"{u}/healthz").status_code == 200


def test_the_health_checks_tell_a_stuck_model_worker(engine, serving):
    stuck = FailingEngine(engine, fail_at=7.0, block_at=9.0)
    blocking = {"joints_2d": [[9.0, 0.0], *SPREAD[1:]]}
    settings = {"ready_stall_s": 0.5, "live_stall_s": 3.0, "request_timeout_s": 20}
    with serving(stuck, **settings) as u:
        waiter = threading.Thread(
            target=lambda: httpx.post(f"{u}/v1/lift", json={"items": [blocking]}, timeout=30)
        )
        waiter.start()
        try:
            assert httpx.get(f"{u}/readyz").status_code == 200
            time.sleep(1.0)
            ready = httpx.get(f"{u}/readyz")
            assert ready.status_code == 503 and ready.json()["error"]["code"] == "stalled"
            assert "ready_stall_s" in ready.json()["error"]["message"]
            assert httpx.get(f"{u}/healthz").status_code == 200
            time.sleep(2.5)
            alive = httpx.get(f"{u}/healthz")
            assert alive.status_code == 503 and "live_stall_s" in alive.text
        finally:
            stuck.release.set()
            waiter.join(30)
        assert httpx.get(f"{u}/readyz").status_code == 200
        assert httpx.get(f"{u}/healthz").status_code == 200
