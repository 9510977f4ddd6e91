"""The service end to end: a real uvicorn on 127.0.0.1 (random free port, in a thread) serving
the bundled Lifter, driven by the client SDK and by raw httpx."""

from __future__ import annotations

import asyncio
import io
import json
import struct
import threading
import time
import zlib
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
import torch
from PIL import Image
from prometheus_client.parser import text_string_to_metric_families

from ds3d.data.lsp import load_lsp
from ds3d.io.images import read_image
from ds3d.kinematics import NODES, Motion, forward_kinematics
from ds3d.skeleton import BONE_NAMES, JOINT_NAMES
from ds3d.util.paths import MODELS_DIR
from ds3d.util.threads import intra_op_threads
from ds3d_service.client import AsyncPoseClient, PoseClient, ServiceError
from ds3d_service.engine import Engine
from ds3d_service.schemas import PersonBox
from ds3d_service.settings import Settings
from tests.needs import missing

# The model the service would serve: $DS3D_MODEL_DIR, else the bundled models/.
MODEL_DIR = Settings().model_dir or MODELS_DIR
if not (MODEL_DIR / "posedb").exists():
    missing(f"no pose database under {MODEL_DIR}", module_level=True)

MAX_IMAGE_BYTES = 100_000
MAX_IMAGE_PIXELS_SIDE = 2000  # the url fixture's max_image_pixels: 2000 x 2000


@pytest.fixture(scope="module")
def url(engine, serving):
    with serving(
        engine,
        max_lift_batch_size=16,
        max_wait_ms=30,
        max_image_bytes=MAX_IMAGE_BYTES,
        max_image_pixels=MAX_IMAGE_PIXELS_SIDE**2,
    ) as u:
        yield u


@pytest.fixture(scope="module")
def poses(data_dir):
    """Real 2D poses (pixels): the first 8 LSP annotations."""
    return load_lsp().joints[:8]


def metric(url: str, name: str, labels: dict) -> dict[str, float]:
    """Samples of metric `name` whose labels include `labels`: {sample name + le: value}."""
    text = httpx.get(f"{url}/metrics").text
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name.startswith(name) and labels.items() <= s.labels.items():
                out[s.name + s.labels.get("le", "")] = s.value
    return out


def wait_for_depth(url: str, depth: int, timeout_s: float = 10) -> None:
    """Wait until `depth` items wait in the lift queue."""
    deadline = time.monotonic() + timeout_s
    while metric(url, "ds3d_queue_depth", {"queue": "lift"})["ds3d_queue_depth"] < depth:
        assert time.monotonic() < deadline, f"queue never reached {depth}"
        time.sleep(0.01)


def test_health_and_readiness(url, engine):
    assert httpx.get(f"{url}/healthz").json()["status"] == "alive"
    ready = httpx.get(f"{url}/readyz")
    assert ready.status_code == 200 and ready.json()["model"] == engine.model_id
    paths = httpx.get(f"{url}/openapi.json").json()["paths"]
    assert {"/v1/lift", "/v1/pose", "/healthz", "/readyz"} <= set(paths)
    pose_body = paths["/v1/pose"]["post"]["requestBody"]["content"]
    assert {"multipart/form-data", "image/*"} <= set(pose_body)
    assert httpx.get(f"{url}/docs").status_code == 200


def test_lift_matches_the_library(url, engine, poses):
    x = poses[:4]
    vis = np.ones((4, 14), bool)
    vis[1, 5] = False
    with PoseClient(url) as client:
        res = client.lift(x, visible=vis)
    # One request's items are queued at once, so they form exactly this batch of 4.
    ref = engine.lifter.lift(x, visible=vis)
    np.testing.assert_allclose(res.joints_3d, ref.joints_3d.numpy(), atol=1e-3)
    np.testing.assert_allclose(res.bone_lengths, ref.bone_lengths.numpy(), atol=1e-3)
    assert res.joint_set == ref.joint_set and res.bone_names == list(BONE_NAMES)
    assert res.model == engine.model_id and res.joint_names == list(JOINT_NAMES)
    assert {"retrieval", "total"} <= set(res.timings_ms)


def test_lift_with_intrinsics_matches_the_library(url, engine, poses):
    k = np.array([[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]], dtype=np.float32)
    with PoseClient(url) as client:
        res = client.lift(poses[4:6], intrinsics=k)
    ref = engine.lifter.lift(poses[4:6], intrinsics=np.stack([k, k]))
    np.testing.assert_allclose(res.joints_3d, ref.joints_3d.numpy(), atol=1e-3)
    assert ref.root_position is not None and res.root_position is not None
    np.testing.assert_allclose(res.root_position, ref.root_position.numpy(), atol=1e-2)
    with PoseClient(url) as client:
        assert client.lift(poses[4:6]).root_position is None  # no camera, nowhere to place


def test_concurrent_requests_share_batches(url, poses):
    before = metric(url, "ds3d_batch_size", {"queue": "lift"})

    async def burst():
        async with AsyncPoseClient(url) as client:
            return await asyncio.gather(*(client.lift(poses[i % 8]) for i in range(24)))

    results = asyncio.run(burst())
    assert all(r.joints_3d.shape == (1, 14, 3) for r in results)
    after = metric(url, "ds3d_batch_size", {"queue": "lift"})
    items = after["ds3d_batch_size_sum"] - before.get("ds3d_batch_size_sum", 0)
    batches = after["ds3d_batch_size_count"] - before.get("ds3d_batch_size_count", 0)
    assert items == 24 and batches < 24  # some batch held more than one request
    requests = metric(url, "ds3d_requests_total", {"route": "/v1/lift", "status": "200"})
    assert requests["ds3d_requests_total"] >= 24
    assert metric(url, "ds3d_stage_seconds_count", {"stage": "retrieval"})


def post_lift(url, body, **kw):
    return httpx.post(f"{url}/v1/lift", json=body, **kw)


def assert_error(resp: httpx.Response, status: int, code: str):
    assert resp.status_code == status, resp.text
    err = resp.json()["error"]
    assert err["code"] == code and err["message"]


def good_item(poses):
    return {"joints_2d": poses[0].tolist()}


def post_raw(url, path, content: bytes | str, ctype: str) -> httpx.Response:
    return httpx.post(f"{url}{path}", content=content, headers={"content-type": ctype})


def test_bad_lift_inputs_get_json_errors(url, poses):
    j = poses[0].tolist()
    json_t = "application/json"
    assert_error(post_raw(url, "/v1/lift", b"{not json", json_t), 422, "invalid_json")
    assert_error(post_raw(url, "/v1/lift", b"", json_t), 422, "invalid_request")
    assert_error(post_raw(url, "/v1/lift", b"hi", "text/plain"), 415, "unsupported_media_type")
    assert_error(post_lift(url, {"items": [{"joints_2d": j[:13]}]}), 422, "invalid_request")
    xyz = [[*p, 0.0] for p in j]
    assert_error(post_lift(url, {"items": [{"joints_2d": xyz}]}), 422, "invalid_request")
    assert_error(post_lift(url, {"items": []}), 422, "invalid_request")
    for bad in ("NaN", "Infinity", "-Infinity", "1e999"):
        raw = '{"items": [{"joints_2d": [[' + bad + ", 1]" + ", [1, 1]" * 13 + "]}]}"
        assert_error(post_raw(url, "/v1/lift", raw, json_t), 422, "invalid_request")
    too_big = [[1e39, 1.0], *j[1:]]  # finite as a double, beyond the schema's bound
    assert_error(post_lift(url, {"items": [{"joints_2d": too_big}]}), 422, "invalid_request")
    # JSON's types, strictly: a boolean is not a number, nor a number a flag.
    k = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, False]]
    assert_error(
        post_lift(url, {"items": [{"joints_2d": j, "intrinsics": k}]}), 422, "invalid_request"
    )
    flags = [1] * 14
    assert_error(
        post_lift(url, {"items": [{"joints_2d": j, "visible": flags}]}), 422, "invalid_request"
    )
    # Bad neighbours did not spoil the service: a good item still gets its answer.
    assert post_lift(url, {"items": [good_item(poses)]}).status_code == 200
    assert httpx.get(f"{url}/readyz").status_code == 200


def jpeg(size=(64, 48)) -> bytes:
    buf = io.BytesIO()
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (*size[::-1], 3), dtype=np.uint8)).save(buf, "JPEG")
    return buf.getvalue()


def png_header(width: int, height: int) -> bytes:
    """A tiny PNG file whose header claims width x height pixels."""

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 64)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def post_image(url, data: bytes, ctype="image/jpeg", multipart=False):
    if multipart:
        return httpx.post(f"{url}/v1/pose", files={"image": ("x", data, ctype)})
    return httpx.post(f"{url}/v1/pose", content=data, headers={"content-type": ctype})


def test_a_request_head_over_the_limit_gets_431_naming_the_setting(url):
    big = {"x-padding": "a" * 20_000}  # over the default max_header_bytes (16 KiB)
    resp = httpx.get(f"{url}/healthz", headers=big)
    assert_error(resp, 431, "headers_too_large")
    assert "max_header_bytes = 16384" in resp.json()["error"]["message"]
    assert httpx.get(f"{url}/healthz", headers={"x-padding": "a" * 8_000}).status_code == 200


@pytest.mark.parametrize("multipart", [False, True])
def test_bad_images_get_json_errors(url, multipart):
    good = jpeg()
    assert_error(post_image(url, b"", multipart=multipart), 422, "invalid_image")
    assert_error(
        post_image(url, b"just some text\n" * 10, multipart=multipart), 422, "invalid_image"
    )
    assert_error(post_image(url, good[: len(good) // 2], multipart=multipart), 422, "invalid_image")
    bomb = png_header(50_000, 50_000)
    assert len(bomb) < 200
    resp = post_image(url, bomb, "image/png", multipart=multipart)
    assert_error(resp, 422, "invalid_image")
    # refused for its size, from the header, naming the setting
    assert "max_image_pixels" in resp.json()["error"]["message"]
    just_over = png_header(MAX_IMAGE_PIXELS_SIDE + 1, MAX_IMAGE_PIXELS_SIDE)
    resp = post_image(url, just_over, "image/png", multipart=multipart)
    assert_error(resp, 422, "invalid_image")
    assert "max_image_pixels" in resp.json()["error"]["message"]
    # Far over (refused on Content-Length) and just over (refused while reading).
    for extra in (70_000, 1_000):
        big = b"\xff\xd8\xff" + b"\0" * (MAX_IMAGE_BYTES + extra)
        resp = post_image(url, big, multipart=multipart)
        assert_error(resp, 413, "payload_too_large")
        assert "max_image_bytes" in resp.json()["error"]["message"]
    assert httpx.get(f"{url}/healthz").status_code == 200


def test_pose_wrong_content_type_and_missing_field(url):
    assert_error(post_image(url, b"hello", "text/plain"), 415, "unsupported_media_type")
    resp = httpx.post(f"{url}/v1/pose", json={"image": "x"})
    assert_error(resp, 415, "unsupported_media_type")
    resp = httpx.post(f"{url}/v1/pose", files={"other": ("x", jpeg())})
    assert_error(resp, 422, "invalid_request")
    resp = httpx.post(
        f"{url}/v1/pose?bbox=[1,2]", content=jpeg(), headers={"content-type": "image/jpeg"}
    )
    assert_error(resp, 422, "invalid_request")


def post_with(url, multipart: bool, **fields) -> httpx.Response:
    """POST /v1/pose of jpeg() with `fields` (JSON text), as form fields beside the image or as
    query parameters beside a raw body."""
    if multipart:
        return httpx.post(
            f"{url}/v1/pose", files={"image": ("x.jpg", jpeg(), "image/jpeg")}, data=fields
        )
    return httpx.post(
        f"{url}/v1/pose", params=fields, content=jpeg(), headers={"content-type": "image/jpeg"}
    )


@pytest.mark.parametrize("multipart", [False, True])
@pytest.mark.parametrize(
    ("box", "why"),
    [
        ({"cx": 1.5, "cy": 0.5, "width": 0.2, "height": 0.5}, "box[cx]"),  # off the image
        ({"cx": 0.5, "cy": 0.5, "width": 0.0, "height": 0.5}, "box[width]"),  # no area
        ({"cx": 0.5, "cy": 0.5, "width": 0.2, "height": 2.5}, "box[height]"),  # too tall
        ({"cx": 0.5, "cy": 0.5, "width": 0.2}, "box[height]: Field required"),
        ({"cx": 0.5, "cy": 0.5, "width": True, "height": 0.5}, "box[width]"),
        ([5, 5, 40, 40], "box: Input should be an object"),  # the corner form as box
    ],
)
def test_pose_box_outside_its_schema_is_a_422_that_says_why(url, multipart, box, why):
    """The box's schema says all its rules: what it refuses, the service refuses, naming the
    field."""
    resp = post_with(url, multipart, box=json.dumps(box))
    assert_error(resp, 422, "invalid_request")
    assert why in resp.json()["error"]["message"]


@pytest.mark.parametrize("multipart", [False, True])
@pytest.mark.parametrize(
    ("bbox", "why"),
    [([50, 10, 5, 40], "no area"), ([5, 5, 5, 40], "no area"), ([900, 900, 990, 990], "outside")],
)
def test_pose_corner_bbox_the_image_cannot_hold_is_a_422_that_says_why(url, multipart, bbox, why):
    """The corner form of earlier clients is still read, and checked by the library."""
    resp = post_with(url, multipart, bbox=json.dumps(bbox))
    assert_error(resp, 422, "invalid_box")
    assert why in resp.json()["error"]["message"]


def test_pose_takes_one_box_and_no_unknown_form_field(url):
    box = {"cx": 0.5, "cy": 0.5, "width": 0.5, "height": 0.9}
    both = post_with(url, True, box=json.dumps(box), bbox="[5, 5, 40, 40]")
    assert_error(both, 422, "invalid_request")
    assert "box or bbox" in both.json()["error"]["message"]
    # an option sent in the form that the query carries would be left out without a word
    unknown = post_with(url, True, people="all")
    assert_error(unknown, 422, "invalid_request")
    assert "['people']" in unknown.json()["error"]["message"]


def test_pose_on_a_valid_image(url, engine):
    with PoseClient(url, retries=0) as client:
        if engine.pipeline is None:
            # The bundled models have no 2D stage: a clear 503, not a crash.
            with pytest.raises(ServiceError) as info:
                client.estimate(jpeg())
            assert (info.value.status, info.value.code) == (503, "model_unavailable")
        else:
            res = client.estimate(jpeg())
            assert res.joints_2d.shape == (14, 2) and res.joints_3d.shape == (14, 3)


def test_pose_matches_the_pipeline(pose_engine, serving):
    path = load_lsp(split="test").image_paths[0]
    image = read_image(path)
    height, width = image.shape[:2]
    box = PersonBox(cx=0.5, cy=0.5, width=1 - 10 / width, height=1 - 10 / height)
    k = [[600.0, 0.0, width / 2], [0.0, 600.0, height / 2], [0.0, 0.0, 1.0]]
    pipeline = pose_engine.pipeline
    # Identical by construction: a request alone in its batch makes the same library call as
    # this reference (one image, its people and min_score), on as many intra-op threads. Only
    # that holds on any machine: the 3D stage's rounding depends on how many poses are lifted
    # together (BLAS chooses its kernels by shape), and the fit can carry a last-bit difference
    # to tenths of a millimetre.
    threads = Settings().torch_threads
    with serving(pose_engine, max_batch_size=8, max_wait_ms=100) as u, PoseClient(u) as client:
        # A file path, sent as multipart.
        res = client.estimate(path)
        with intra_op_threads(threads):
            ref = pipeline.estimate([image])
        np.testing.assert_allclose(res.joints_2d, ref.joints_2d[0].numpy(), atol=1e-2)
        np.testing.assert_allclose(res.joints_3d, ref.joints_3d[0].numpy(), atol=1e-2)
        assert res.joint_set == ref.joint_set[0] and res.confidence.shape == (14,)
        assert res.facing_camera == pytest.approx(float(ref.facing_camera[0]), abs=1e-6)
        assert {"2d_features", "total"} <= set(res.timings_ms)
        # Placed by an assumed camera, or by the focal length given.
        assert res.focal_assumed and res.root_position is not None
        np.testing.assert_allclose(res.root_position, ref.root_position[0].numpy(), atol=1e-1)
        np.testing.assert_allclose(res.joints_3d_camera, res.joints_3d + res.root_position)
        given = client.estimate(path, focal_px=900.0, angles=True)
        assert given.focal_px == 900.0 and given.focal_assumed is False
        assert given.angles is not None and given.angles["nodes"][0] == "hips"
        assert client.estimate(path).angles is None
        # Joint angles on request: forward kinematics of them places the joints as answered.
        asked = httpx.post(
            f"{u}/v1/pose", params={"angles": "true"}, content=path.read_bytes(),
            headers={"content-type": "image/jpeg"}, timeout=60,
        )  # fmt: skip
        person = asked.json()
        angles = person["angles"]
        assert angles["nodes"][0] == "hips" and len(angles["rotations"]) == len(NODES)
        w, x, y, z = torch.tensor(angles["rotations"], dtype=torch.float64).unbind(-1)
        turns = torch.stack(
            [
                1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
            ],
            -1,
        ).view(1, -1, 3, 3)  # fmt: skip
        motion = Motion(
            torch.tensor(angles["offsets"]), torch.tensor([angles["root"]]).double(), turns
        )
        placed = np.asarray(person["joints_3d_camera"]) * [1, -1, -1]
        np.testing.assert_allclose(forward_kinematics(motion)[0], placed, atol=0.05)
        # Raw JPEG body, box and intrinsics as query parameters: the box made the corners it
        # says, the same as the corner form of earlier clients gives.
        corners = box.corners(width, height)
        with intra_op_threads(threads):
            ref = pipeline.estimate([image], [corners], intrinsics=np.asarray(k)[None])
        for name, value in (("box", box.model_dump_json()), ("bbox", json.dumps(corners.tolist()))):
            params = {name: value, "intrinsics": json.dumps(k)}
            raw = httpx.post(
                f"{u}/v1/pose", params=params, content=path.read_bytes(),
                headers={"content-type": "image/jpeg"}, timeout=60,
            )  # fmt: skip
            assert raw.status_code == 200, raw.text
            answer = raw.json()["joints_3d"]
            np.testing.assert_allclose(answer, ref.joints_3d[0].numpy(), atol=1e-2)
        # Concurrent numpy images (sent as PNG) share batches and keep their own results.
        before = metric(u, "ds3d_batch_size", {"queue": "pose"}).get("ds3d_batch_size_count", 0)
        many = client.estimate_many([image, image[:, ::-1].copy()] * 2, concurrency=4)
        batches = metric(u, "ds3d_batch_size", {"queue": "pose"})["ds3d_batch_size_count"] - before
        assert batches < 4
        np.testing.assert_allclose(many[0].joints_2d, res.joints_2d, atol=1e-2)
        np.testing.assert_allclose(many[2].joints_2d, many[0].joints_2d, atol=1e-2)
        assert not np.allclose(many[1].joints_2d, many[0].joints_2d)


def test_full_queue_answers_503_at_once(engine, poses, serving):
    # The batch waits up to 2 s for company, so the first request's items stay queued.
    with serving(engine, max_lift_queue=4, max_lift_batch_size=64, max_wait_ms=2000) as u:
        first: list[httpx.Response] = []
        waiter = threading.Thread(
            target=lambda: first.append(post_lift(u, {"items": [good_item(poses)] * 4}))
        )
        waiter.start()
        wait_for_depth(u, 4)
        assert_error(httpx.get(f"{u}/readyz"), 503, "saturated")
        t0 = time.perf_counter()
        resp = post_lift(u, {"items": [good_item(poses)]})
        assert time.perf_counter() - t0 < 1.0  # refused at once, not after the wait
        assert_error(resp, 503, "overloaded")
        assert "max_lift_queue" in resp.json()["error"]["message"]
        assert resp.headers["retry-after"] == "1"
        assert httpx.get(f"{u}/healthz").status_code == 200
        # More items than the queue holds can never fit: 413, nothing to retry.
        resp = post_lift(u, {"items": [good_item(poses)] * 5})
        assert_error(resp, 413, "too_many_items")
        assert "over max_lift_queue = 4" in resp.json()["error"]["message"]
        waiter.join(30)
        assert first[0].status_code == 200 and len(first[0].json()["items"]) == 4
        assert httpx.get(f"{u}/readyz").status_code == 200


def test_past_the_deadline_answers_504_and_stays_healthy(engine, poses, serving):
    # The batch waits 300 ms for company, the deadline is 50 ms.
    with serving(engine, max_lift_batch_size=64, max_wait_ms=300, request_timeout_s=0.05) as u:
        resp = post_lift(u, {"items": [good_item(poses)]})
        assert_error(resp, 504, "timeout")
        assert "request_timeout_s" in resp.json()["error"]["message"]
        assert httpx.get(f"{u}/healthz").status_code == 200
        assert httpx.get(f"{u}/readyz").status_code == 200
        counts = metric(u, "ds3d_requests_total", {"route": "/v1/lift", "status": "504"})
        assert counts["ds3d_requests_total"] == 1


def test_shutdown_answers_the_queued_requests(engine, poses, serving):
    results: list[int] = []

    def call(u):
        results.append(post_lift(u, {"items": [good_item(poses)]}, timeout=30).status_code)

    with serving(engine, max_lift_batch_size=64, max_wait_ms=1000) as u:
        threads = [threading.Thread(target=call, args=(u,)) for _ in range(4)]
        for t in threads:
            t.start()
        wait_for_depth(u, 4)  # all four wait in the queue for the batch to fill
    # Leaving the block stopped the server: it drained the queue before exiting.
    for t in threads:
        t.join(30)
    assert results == [200] * 4


def test_loadtest_tool_writes_its_report(url, poses, tmp_path):
    from tools import loadtest

    poses_file = tmp_path / "poses.json"
    poses_file.write_text(json.dumps({"joints_2d": poses.tolist()}))
    args = [url, "--poses", str(poses_file), "--concurrency", "2", "--duration", "1"]
    assert loadtest.main([*args, "--out", str(tmp_path), "--name", "t"]) == 0
    report = json.loads((tmp_path / "t.json").read_text())
    assert report["status_counts"].get("200", 0) >= 1 and report["health_after"]["/healthz"] == 200
    assert report["latency_ms_ok"]["p50"] > 0 and (tmp_path / "t.png").stat().st_size > 0
    with pytest.raises(SystemExit):
        loadtest.parse_args(["http://example.com:8000"])  # only local targets


def test_people_all_and_nobody(engine, serving, data_dir):
    """A canvas of two LSP test people: people=all answers both (boxes matching theirs), the
    default answers one of them, found (the search's likeliest proposal alone, whose 2D score
    need not be the best of all's); a blank image answers nobody, and person_found false."""
    if engine.pipeline is None:
        missing("the bundled models have no 2D stage")
    from ds3d.boxes import iou
    from ds3d.evaluation.canvases import compose

    canvas = compose(load_lsp(split="test"), [3, 8], [0.8, 0.5], np.random.default_rng(0))
    assert len(canvas.sources) == 2
    with serving(engine, max_wait_ms=30) as u, PoseClient(u, retries=0) as client:
        people = client.find_people(canvas.image)
        assert len(people) >= 2 and [p.score for p in people] == sorted(
            [p.score for p in people], reverse=True
        )
        overlap = iou(np.stack([p.box for p in people]), canvas.boxes())
        assert (overlap.max(0) >= 0.5).all(), overlap
        best = client.estimate(canvas.image)
        assert best.person_found and best.box is not None
        assert iou(best.box[None], np.stack([p.box for p in people])).max() >= 0.5
        blank = np.full((480, 640, 3), 128, np.uint8)
        assert client.find_people(blank) == []
        nobody = client.estimate(blank)
        assert not nobody.person_found and nobody.joints_2d.shape == (14, 2)
        # a box given skips the search: the person is where the caller says
        boxed = client.estimate(blank, bbox=[100, 100, 300, 400])
        assert boxed.person_found


@pytest.mark.slow
def test_pose_on_worker_processes_answers_as_one_process(engine, serving, data_dir):
    """DS3D_WORKERS=2: /v1/pose's batches split between two processes of the bundled models
    answer as the pipeline of this process does (2D alike, 3D up to the fit's rounding, which
    depends on how many people are lifted together); /metrics' resident memory counts the
    workers' (each holds the models: over 100 MB) beside the server's."""
    paths = load_lsp(split="test").image_paths[:4]
    pooled = Engine.load(MODEL_DIR, "cpu", workers=2, threads=1)
    try:
        with serving(pooled, max_batch_size=4, max_wait_ms=200) as u, PoseClient(u) as client:
            with ThreadPoolExecutor(4) as calls:
                answers = list(calls.map(client.estimate, paths))
            own = metric(u, "process_resident_memory_bytes", {})
            together = metric(u, "ds3d_resident_memory_bytes", {})
            assert together["ds3d_resident_memory_bytes"] > (
                own["process_resident_memory_bytes"] + 2 * 100 * 2**20
            )
    finally:
        pooled.close()
    ref = engine.pipeline.estimate([read_image(p) for p in paths])
    for i, res in enumerate(answers):
        np.testing.assert_allclose(res.joints_2d, ref.joints_2d[i].numpy(), atol=1e-2)
        np.testing.assert_allclose(res.joints_3d, ref.joints_3d[i].numpy(), atol=1.0)
