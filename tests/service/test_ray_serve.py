"""The API on Ray Serve (ds3d_service/ray_serve.py): a local single-node Ray, one replica serving a
--small 2D model on a free port of 127.0.0.1, driven by raw httpx; answers as the plain
service's. Needs ray (the optional extra `ray`) and the datasets (tests/needs.py)."""

from __future__ import annotations

import asyncio
import socket

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from tests.needs import missing

try:
    import ray
    from ray import serve

    from ds3d_service.ray_serve import ServeQueue, app_builder, http_options
except ImportError as exc:
    missing(f"ray[serve] is not installed ({exc}): pip install -e .[ray]", module_level=True)

from ds3d.data.lsp import load_lsp
from ds3d.skeleton import JOINT_NAMES
from ds3d_service.app import create_app
from ds3d_service.microbatch import CallerQueueFull, DeadlineExceeded, ItemFailed, QueueFull
from ds3d_service.settings import Settings

pytestmark = pytest.mark.slow
RETRY_AFTER_S = 2


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def url(model_dir):
    """One replica of the deployment, small backpressure bounds (2 requests in the replica, 4
    waiting in the proxy), served on 127.0.0.1."""
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        object_store_memory=200 * 1024**2,
        log_to_driver=False,
    )
    try:
        settings = Settings(port=free_port(), retry_after_s=RETRY_AFTER_S)
        serve.start(http_options=http_options(settings))
        args = {
            "model_dir": str(model_dir),
            "max_wait_ms": 30,
            "retry_after_s": RETRY_AFTER_S,
            "min_replicas": 1,
            "max_replicas": 1,
            "max_ongoing_requests": 2,
            "max_queued_requests": 4,
        }
        serve.run(app_builder(args), name="ds3d", route_prefix="/")
        yield f"http://127.0.0.1:{settings.port}"
    finally:
        serve.shutdown()
        ray.shutdown()


@pytest.fixture(scope="module")
def lsp():
    return load_lsp(split="test")


def test_health_and_readiness(url):
    alive = httpx.get(f"{url}/healthz", headers={"x-request-id": "probe-1"})
    assert alive.json()["status"] == "alive"
    assert alive.headers.get_list("x-request-id") == ["probe-1"]  # once, not Ray's and ours
    assert alive.headers["x-content-type-options"] == "nosniff"  # the access guard ran
    ready = httpx.get(f"{url}/readyz")
    assert ready.status_code == 200, ready.text
    assert ready.json()["status"] == "ready" and ready.json()["pose_available"] is True


def test_lift_matches_the_library(url, lsp, lifter):
    x = lsp.joints[:4]
    resp = httpx.post(f"{url}/v1/lift", json={"items": [{"joints_2d": p.tolist()} for p in x]})
    assert resp.status_code == 200, resp.text
    body = resp.json()
    ref = lifter.lift(x)
    np.testing.assert_allclose(
        [it["joints_3d"] for it in body["items"]], ref.joints_3d.numpy(), atol=1e-3
    )
    assert body["joint_names"] == list(JOINT_NAMES) and body["model"] == lifter.model_id
    # The request's items were queued at once: one batch of 4 (the replica's own metrics).
    metrics = {
        (s.name, s.labels.get("queue")): s.value
        for family in text_string_to_metric_families(httpx.get(f"{url}/metrics").text)
        for s in family.samples
    }
    assert metrics["ds3d_batch_size_count", "lift"] == 1
    assert metrics["ds3d_batch_size_sum", "lift"] == 4


def test_a_bad_item_fails_only_its_request(url, lsp):
    good = {"joints_2d": lsp.joints[0].tolist()}
    bad = {"joints_2d": lsp.joints[1].tolist(), "visible": [False] * 14}  # the library refuses

    async def together():
        async with httpx.AsyncClient(base_url=url, timeout=30) as client:
            return await asyncio.gather(
                client.post("/v1/lift", json={"items": [good, bad]}),
                client.post("/v1/lift", json={"items": [good, good]}),
            )

    spoiled, fine = asyncio.run(together())
    assert spoiled.status_code == 422, spoiled.text
    err = spoiled.json()["error"]
    assert err["code"] == "invalid_pose" and err["message"].startswith("items[1]: ")
    assert fine.status_code == 200, fine.text


def test_pose_on_an_lsp_image_and_a_bad_image(url, lsp):
    image = lsp.image_paths[0].read_bytes()
    resp = httpx.post(f"{url}/v1/pose", content=image, headers={"content-type": "image/jpeg"})
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert np.shape(body["joints_2d"]) == (14, 2) and np.shape(body["joints_3d"]) == (14, 3)
    files = {"image": ("x.jpg", image, "image/jpeg")}
    assert httpx.post(f"{url}/v1/pose", files=files, timeout=30).status_code == 200

    text = b"just some text\n" * 10
    resp = httpx.post(f"{url}/v1/pose", content=text, headers={"content-type": "image/jpeg"})
    # The plain service's answer (an image is checked before the models are needed).
    plain = TestClient(create_app(Settings())).post(
        "/v1/pose", content=text, headers={"content-type": "image/jpeg"}
    )
    assert resp.status_code == plain.status_code == 422
    assert resp.json() == plain.json() and resp.json()["error"]["code"] == "invalid_image"


def test_overload_answers_503_with_retry_after(url, lsp):
    image = lsp.image_paths[0].read_bytes()

    async def burst():
        limits = httpx.Limits(max_connections=32)
        async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits) as client:
            return await asyncio.gather(
                *(
                    client.post("/v1/pose", content=image, headers={"content-type": "image/jpeg"})
                    for _ in range(24)
                )
            )

    responses = asyncio.run(burst())
    statuses = [r.status_code for r in responses]
    assert set(statuses) <= {200, 503} and 200 in statuses and 503 in statuses, statuses
    refused = next(r for r in responses if r.status_code == 503)
    assert refused.headers["retry-after"] == str(RETRY_AFTER_S)
    assert httpx.get(f"{url}/readyz").status_code == 200


# ServeQueue alone: the MicroBatcher interface on an item function (no Ray needed).


async def _double(x):
    await asyncio.sleep(0.01)
    return ValueError(f"bad {x}") if x < 0 else 2 * x


def test_serve_queue_answers_as_micro_batcher():
    async def scenario():
        q = ServeQueue(_double, max_queue=4, max_queue_per_caller=3)
        assert await q.submit_many([1, 2], 1.0) == [2, 4]
        with pytest.raises(ItemFailed) as failed:
            await q.submit_many([1, -1], 1.0)
        assert failed.value.index == 1 and isinstance(failed.value.cause, ValueError)
        with pytest.raises(ValueError):
            await q.submit(-1, 1.0)
        with pytest.raises(QueueFull):
            await q.submit_many([1] * 5, 1.0)
        first = asyncio.ensure_future(q.submit_many([1, 2], 1.0, "a"))
        await asyncio.sleep(0)
        with pytest.raises(CallerQueueFull):
            await q.submit_many([1, 2], 1.0, "a")
        assert await q.submit(3, 1.0, "b") == 6
        assert await first == [2, 4] and q.depth == 0
        with pytest.raises(DeadlineExceeded):
            await q.submit(1, 0.001)
        assert q.depth == 0

    asyncio.run(scenario())
