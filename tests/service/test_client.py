"""The client SDK on its own: request encoding, error decoding, the retry policy, and that it
imports neither torch, faiss nor fastapi. Responses come from an httpx MockTransport (the
transport layer, not a model); the SDK against the real service is in test_app.py."""

from __future__ import annotations

import asyncio
import io
import json
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
from PIL import Image

from ds3d_service.client import (
    AsyncPoseClient,
    PoseClient,
    ServiceError,
    encode_png,
    person_box,
)


def lift_answer(request: httpx.Request) -> httpx.Response:
    items = json.loads(request.content)["items"]
    out = [
        {
            "joints_3d": [[i, 0.0, 1.0]] * 14,
            "bone_lengths": [100.0 + i] * 14,
            "joint_set": "all",
            "energy": 0.5,
        }
        for i in range(len(items))
    ]
    body = {"items": out, "joint_names": ["j"] * 14, "bone_names": ["b"] * 14, "model": "m"}
    return httpx.Response(200, json=body | {"timings_ms": {"total": 1.0}})


class Flaky:
    """503 with Retry-After for the first `fails` calls, then lift answers."""

    def __init__(self, fails: int, retry_after: str = "0"):
        self.fails, self.retry_after, self.calls = fails, retry_after, 0

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.calls += 1
        if self.calls <= self.fails:
            err = {"error": {"code": "overloaded", "message": "queue full"}}
            return httpx.Response(503, json=err, headers={"Retry-After": self.retry_after})
        return lift_answer(request)


def test_sdk_imports_no_heavy_libraries():
    code = (
        "import sys, ds3d_service.client; "
        "print(sorted({'torch','faiss','fastapi'} & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_lift_encodes_a_batch_and_decodes_typed_arrays():
    seen = []

    def handler(request):
        seen.append(json.loads(request.content))
        return lift_answer(request)

    client = PoseClient("http://svc", transport=httpx.MockTransport(handler))
    x = np.arange(3 * 14 * 2, dtype=np.float32).reshape(3, 14, 2)
    k = np.array([[1000, 0, 500], [0, 1000, 500], [0, 0, 1]], dtype=np.float32)
    res = client.lift(x, intrinsics=k, visible=np.ones(14, bool))
    body = seen[0]["items"]
    assert len(body) == 3 and np.array_equal(np.asarray(body[2]["joints_2d"]), x[2])
    assert body[1]["intrinsics"] == k.tolist() and body[0]["visible"] == [True] * 14
    assert res.joints_3d.shape == (3, 14, 3) and res.joints_3d.dtype == np.float32
    assert res.joints_3d[2, 0, 0] == 2 and res.joint_set == ["all"] * 3 and res.model == "m"
    assert res.bone_lengths.shape == (3, 14) and res.bone_lengths[2, 0] == 102
    # one pose (14, 2) is a batch of one
    assert client.lift(x[0]).joints_3d.shape == (1, 14, 3)
    with pytest.raises(ValueError):
        client.lift(np.zeros((14, 3)))


def test_503_is_retried_honouring_retry_after_then_succeeds():
    flaky = Flaky(fails=2, retry_after="0")
    client = PoseClient("http://svc", retries=3, transport=httpx.MockTransport(flaky))
    assert client.lift(np.zeros((14, 2))).joints_3d.shape == (1, 14, 3)
    assert flaky.calls == 3


def test_retries_run_out_and_the_error_is_typed():
    flaky = Flaky(fails=10, retry_after="0")
    client = PoseClient("http://svc", retries=2, transport=httpx.MockTransport(flaky))
    with pytest.raises(ServiceError) as info:
        client.lift(np.zeros((14, 2)))
    assert flaky.calls == 3
    assert (info.value.status, info.value.code, info.value.retry_after) == (503, "overloaded", 0.0)


def test_other_errors_are_not_retried():
    calls = []

    def handler(request):
        calls.append(1)
        return httpx.Response(422, json={"error": {"code": "invalid_pose", "message": "NaN"}})

    client = PoseClient("http://svc", retries=3, transport=httpx.MockTransport(handler))
    with pytest.raises(ServiceError) as info:
        client.lift(np.zeros((14, 2)))
    assert len(calls) == 1 and info.value.code == "invalid_pose"


def test_retry_after_sets_the_wait(monkeypatch):
    waits: list[float] = []
    monkeypatch.setattr(time, "sleep", waits.append)  # record the waits instead of sleeping
    busy = Flaky(fails=10, retry_after="2")
    client = PoseClient("http://svc", retries=1, backoff_s=0.0, transport=httpx.MockTransport(busy))
    with pytest.raises(ServiceError):
        client.lift(np.zeros((14, 2)))
    assert waits == [2.0]  # Retry-After, not the (zero) backoff; then the retries were spent
    assert busy.calls == 2
    timeout = httpx.MockTransport(lambda request: httpx.Response(504))
    client = PoseClient("http://svc", retries=1, backoff_s=0.0, transport=timeout)
    with pytest.raises(ServiceError):
        client.lift(np.zeros((14, 2)))
    assert waits == [2.0]  # a 504 is not waited on: no retry


def test_a_dropped_connection_and_a_502_are_retried_a_timeout_is_not():
    """A replica killed mid-request closes the connection (RemoteProtocolError, ReadError); a
    balancer with no live replica answers 502: both retried. A read timeout is not."""
    outcomes = [
        httpx.RemoteProtocolError("Server disconnected without sending a response."),
        httpx.ReadError("connection reset by peer"),
        httpx.Response(502, text="<html>bad gateway</html>"),
    ]

    def dying(request):
        if outcomes:
            outcome = outcomes.pop(0)
            if isinstance(outcome, Exception):
                raise outcome
            return outcome
        return lift_answer(request)

    client = PoseClient(
        "http://svc", retries=3, backoff_s=0.0, transport=httpx.MockTransport(dying)
    )
    assert client.lift(np.zeros((14, 2))).joints_3d.shape == (1, 14, 3) and not outcomes

    calls = []

    def slow(request):
        calls.append(1)
        raise httpx.ReadTimeout("timed out")

    client = PoseClient("http://svc", retries=3, backoff_s=0.0, transport=httpx.MockTransport(slow))
    with pytest.raises(httpx.ReadTimeout):
        client.lift(np.zeros((14, 2)))
    assert len(calls) == 1


def test_async_twin_shares_the_behaviour():
    flaky = Flaky(fails=1)

    async def main():
        async with AsyncPoseClient("http://svc", transport=httpx.MockTransport(flaky)) as client:
            return await client.lift(np.zeros((2, 14, 2)))

    res = asyncio.run(main())
    assert res.joints_3d.shape == (2, 14, 3) and flaky.calls == 2


def test_estimate_sends_a_numpy_image_as_png_with_bbox():
    seen = {}

    def handler(request: httpx.Request):
        seen["ctype"] = request.headers["content-type"]
        seen["body"] = request.read()
        return httpx.Response(
            200,
            json={
                "joint_names": ["j"] * 14,
                "joints_2d": [[1.0, 2.0]] * 14,
                "joints_3d": [[1.0, 2.0, 3.0]] * 14,
                "confidence": [0.5] * 14,
                "facing_camera": 0.25,
                "joint_set": "up",
                "model": "m",
                "timings_ms": {},
            },
        )

    client = PoseClient("http://svc", transport=httpx.MockTransport(handler))
    img = np.random.default_rng(0).integers(0, 255, (6, 9, 3), dtype=np.uint8)
    res = client.estimate(img, bbox=[1, 2, 3, 4])
    assert seen["ctype"].startswith("multipart/form-data")
    # the corners as the API's box: centre and sides as fractions of the 9 x 6 px image
    sent = json.dumps({"cx": 2 / 9, "cy": 3 / 6, "width": 2 / 9, "height": 2 / 6})
    assert b"\x89PNG" in seen["body"] and sent.encode() in seen["body"]
    assert res.joints_2d.shape == (14, 2) and res.confidence.shape == (14,)
    assert res.facing_camera == 0.25
    assert res.joint_set == "up"


def test_a_box_of_an_image_file_is_a_fraction_of_its_upright_size(tmp_path):
    """A photo stored 40 x 20 px and turned a quarter by its EXIF orientation is 20 x 40 px
    upright, as the service reads it: the box's fractions are of that."""
    exif = Image.Exif()
    exif[0x0112] = 6  # Orientation: turn 90 degrees clockwise
    path = tmp_path / "turned.jpg"
    Image.new("RGB", (40, 20)).save(path, exif=exif)
    sent = {}

    def handler(request: httpx.Request):
        sent["body"] = request.read()
        return httpx.Response(503, json={"error": {"code": "busy", "message": "stop here"}})

    client = PoseClient("http://svc", retries=0, transport=httpx.MockTransport(handler))
    with pytest.raises(ServiceError):
        client.estimate(path, bbox=[2, 4, 12, 36])
    assert json.dumps(person_box([2, 4, 12, 36], 20, 40)).encode() in sent["body"]
    assert person_box([2, 4, 12, 36], 20, 40) == {
        "cx": 0.35,
        "cy": 0.5,
        "width": 0.5,
        "height": 0.8,
    }
    with pytest.raises(ValueError, match="not x, y, width, height"):
        client.estimate(path, bbox=[2, 4, 10, 4])  # no height: x, y, width, height mistaken


def test_encode_png_round_trips():
    img = np.random.default_rng(1).integers(0, 255, (7, 5, 3), dtype=np.uint8)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(encode_png(img)))), img)
    with pytest.raises(ValueError):
        encode_png(img.astype(np.float32))
