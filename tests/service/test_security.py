"""Who may call the service (ds3d_service/access/keys.py, ds3d_service/fairness.py, the middleware
in ds3d_service/app.py): API keys on every route, keys never in URLs, per-caller limits, CORS, the
browser headers, logs without secrets, and an audit of the installed dependencies."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from ds3d_service.access.keys import ApiKeys, InvalidKeys, key_id, presented_key, read_keys
from ds3d_service.client import PoseClient, ServiceError
from tests.needs import missing

KEY_A = "a-first-test-key-0123456789"
KEY_B = "b-second-test-key-0123456789"


def test_keys_come_comma_separated_or_from_a_file(tmp_path):
    assert read_keys(f" {KEY_A}, {KEY_B} ,") == [KEY_A, KEY_B]
    path = tmp_path / "keys.txt"
    path.write_text(f"# the team's keys\n{KEY_A}\n\n{KEY_B}  # ci\n")
    assert read_keys(str(path)) == [KEY_A, KEY_B]
    with pytest.raises(InvalidKeys, match="shorter than 16"):
        read_keys(f"{KEY_A},short")
    with pytest.raises(InvalidKeys, match="no key"):
        read_keys(" , ")


def test_a_key_is_recognised_by_its_digest_only():
    keys = ApiKeys([KEY_A, KEY_B])
    assert keys.check(KEY_B) == key_id(KEY_B) and len(key_id(KEY_B)) == 8
    assert keys.check(KEY_A + "x") is None and keys.check("") is None
    assert KEY_A not in repr(vars(keys))  # digests only in memory


def test_the_key_is_read_from_bearer_or_x_api_key():
    assert presented_key({"authorization": f"Bearer {KEY_A}"}) == KEY_A
    assert presented_key({"authorization": f"bearer  {KEY_A} "}) == KEY_A
    assert presented_key({"x-api-key": KEY_B}) == KEY_B
    assert presented_key({"authorization": f"Basic {KEY_A}"}) is None
    assert presented_key({}) is None


# A standing person in LSP joint order (pixels): enough for /v1/lift to answer.
STANDING = [
    [120, 400], [122, 320], [125, 240], [155, 240], [158, 320], [160, 400], [95, 230],
    [100, 180], [115, 130], [165, 130], [180, 180], [185, 230], [140, 120], [140, 70],
]  # fmt: skip
LIFT = {"items": [{"joints_2d": STANDING}]}


def jpeg() -> bytes:
    return cv2.imencode(".jpg", np.full((96, 64, 3), 128, np.uint8))[1].tobytes()


def bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def assert_refused(resp: httpx.Response, status: int, code: str) -> None:
    assert resp.status_code == status, resp.text
    assert resp.json()["error"]["code"] == code


@pytest.fixture(scope="module")
def keyed(engine, serving):
    """A service that needs a key (KEY_A or KEY_B) on /v1/* and /metrics."""
    with serving(engine, api_keys=f"{KEY_A},{KEY_B}", max_wait_ms=5) as url:
        yield url


def calls(url: str) -> dict[str, Callable[..., httpx.Response]]:
    """A request to every route that needs a key, by name; each takes the request headers."""
    image = {"image": ("p.jpg", jpeg(), "image/jpeg")}
    return {
        "lift": lambda h: httpx.post(f"{url}/v1/lift", json=LIFT, headers=h),
        "pose": lambda h: httpx.post(f"{url}/v1/pose", files=image, headers=h, timeout=60),
        "metrics": lambda h: httpx.get(f"{url}/metrics", headers=h),
    }


def test_every_api_route_needs_a_right_key(keyed):
    for name, call in calls(keyed).items():
        for headers in ({}, bearer("not-the-key-0123456789"), {"X-API-Key": KEY_A + "0"}):
            resp = call(headers)
            assert_refused(resp, 401, "unauthorized")
            assert resp.headers["www-authenticate"].startswith("Bearer"), name
        assert call(bearer(KEY_A)).status_code == 200, name
        assert call({"X-API-Key": KEY_B}).status_code == 200, name
    for path in ("/healthz", "/readyz", "/docs", "/openapi.json"):  # probes and the API's docs
        assert httpx.get(f"{keyed}{path}").status_code == 200, path
    schemes = httpx.get(f"{keyed}/openapi.json").json()["components"]["securitySchemes"]
    assert set(schemes) == {"HTTPBearer", "APIKeyHeader"}  # /docs offers to send a key


def test_a_key_in_the_url_is_refused_even_with_a_right_header(keyed):
    for query in (f"api_key={KEY_A}", f"token={KEY_A}", f"key={KEY_A}"):
        resp = httpx.post(f"{keyed}/v1/lift?{query}", json=LIFT, headers=bearer(KEY_A))
        assert_refused(resp, 400, "key_in_url")
        assert KEY_A not in resp.text


def test_metrics_can_be_made_public(engine, serving):
    with serving(engine, api_keys=KEY_A, metrics_public=True) as url:
        assert httpx.get(f"{url}/metrics").status_code == 200
        assert_refused(httpx.post(f"{url}/v1/lift", json=LIFT), 401, "unauthorized")


def test_without_keys_every_caller_is_served(engine, serving):
    with serving(engine) as url:
        assert httpx.post(f"{url}/v1/lift", json=LIFT).status_code == 200
        assert httpx.get(f"{url}/metrics").status_code == 200


@pytest.mark.slow
def test_no_keys_with_keys_required_refuses_to_start(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("DS3D_API_KEYS")}
    command = [sys.executable, "-m", "ds3d_service", "--require-api-keys", "true", "--port", "0"]
    out = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "DS3D_API_KEYS" in out.stderr, out.stderr
    keys = tmp_path / "keys"
    keys.write_text("short\n")
    command += ["--api-keys", str(keys)]
    out = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "shorter than 16" in out.stderr, out.stderr


def test_the_rate_limit_trips_per_caller_and_recovers(engine, serving):
    keys = f"{KEY_A},{KEY_B}"
    with serving(engine, api_keys=keys, rate_limit_rps=2, rate_limit_burst=3) as url:
        lift = calls(url)["lift"]
        assert [lift(bearer(KEY_A)).status_code for _ in range(3)] == [200] * 3
        resp = lift(bearer(KEY_A))
        assert_refused(resp, 429, "rate_limited")
        assert int(resp.headers["retry-after"]) >= 1
        assert "rate_limit_rps" in resp.json()["error"]["message"]
        assert lift(bearer(KEY_B)).status_code == 200  # the other caller is not held back
        time.sleep(1.0)  # two tokens back
        assert lift(bearer(KEY_A)).status_code == 200
        assert httpx.get(f"{url}/healthz").status_code == 200  # probes are never limited


def test_one_caller_cannot_fill_the_queue_for_the_others(engine, serving):
    """Lift queue of 8, a caller's share 4: a caller with 4 items waiting is refused one more
    (429), another caller still gets in."""
    settings = dict(api_keys=f"{KEY_A},{KEY_B}", max_lift_queue=8, max_wait_ms=1500)
    with serving(engine, max_lift_batch_size=64, **settings) as url:
        waiting: list[httpx.Response] = []
        greedy = threading.Thread(
            target=lambda: waiting.append(
                httpx.post(
                    f"{url}/v1/lift", json={"items": LIFT["items"] * 4}, headers=bearer(KEY_A)
                )
            )
        )
        greedy.start()
        time.sleep(0.5)  # its 4 items wait for company
        resp = httpx.post(f"{url}/v1/lift", json=LIFT, headers=bearer(KEY_A))
        assert_refused(resp, 429, "caller_queue_full")
        assert "caller_queue_share" in resp.json()["error"]["message"]
        assert "retry-after" in resp.headers
        assert httpx.post(f"{url}/v1/lift", json=LIFT, headers=bearer(KEY_B)).status_code == 200
        greedy.join(30)
        assert waiting[0].status_code == 200


def test_cors_is_off_by_default_and_follows_the_allow_list(engine, serving, keyed):
    preflight = {
        "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "authorization,content-type",
    }
    allowed, refused = "https://app.example.org", "https://elsewhere.example.com"
    resp = httpx.options(f"{keyed}/v1/lift", headers={"Origin": allowed, **preflight})
    assert "access-control-allow-origin" not in resp.headers  # no allow-list, no CORS
    with serving(engine, api_keys=KEY_A, cors_origins=allowed) as url:
        resp = httpx.options(f"{url}/v1/lift", headers={"Origin": allowed, **preflight})
        assert resp.status_code == 200
        assert resp.headers["access-control-allow-origin"] == allowed
        assert "authorization" in resp.headers["access-control-allow-headers"].lower()
        resp = httpx.options(f"{url}/v1/lift", headers={"Origin": refused, **preflight})
        assert resp.status_code == 400 and "access-control-allow-origin" not in resp.headers
        # an answer to the allowed origin (a refusal too) is readable by its page
        resp = httpx.post(f"{url}/v1/lift", json=LIFT, headers={"Origin": allowed})
        assert resp.status_code == 401
        assert resp.headers["access-control-allow-origin"] == allowed


def test_answers_carry_a_request_id_and_the_browser_headers(keyed):
    resp = httpx.post(
        f"{keyed}/v1/lift", json=LIFT, headers=bearer(KEY_A) | {"X-Request-ID": "abc-123"}
    )
    assert resp.headers["x-request-id"] == "abc-123"
    refused = httpx.post(f"{keyed}/v1/lift", json=LIFT, headers={"X-Request-ID": "<script>"})
    assert (
        refused.headers["x-request-id"] != "<script>" and len(refused.headers["x-request-id"]) == 32
    )
    for r in (resp, refused, httpx.get(f"{keyed}/healthz")):
        assert r.headers["x-content-type-options"] == "nosniff"
        assert r.headers["referrer-policy"] == "no-referrer"
        assert r.headers["x-frame-options"] == "DENY"


def test_the_access_log_names_the_key_by_its_id_never_the_key(keyed, caplog):
    caplog.set_level(logging.INFO, logger="ds3d_service.access.rules")
    headers = bearer(KEY_A) | {"X-Request-ID": "log-check-1"}
    httpx.post(f"{keyed}/v1/lift?people=all", json=LIFT, headers=headers)
    httpx.post(f"{keyed}/v1/lift", json=LIFT, headers=bearer("wrong-key-0123456789abc"))

    def logged() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.name == "ds3d_service.access.rules"]

    # The server's thread logs a request once it has answered: wait for the second line.
    deadline = time.monotonic() + 10
    while len(logged()) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    lines = logged()
    mine = [line for line in lines if line.startswith("log-check-1 ")]
    assert mine and f"key:{key_id(KEY_A)}" in mine[0] and "people=all" not in mine[0]
    text = "\n".join(lines)
    assert KEY_A not in text and "wrong-key" not in text and "refused" in text


def test_the_sdk_sends_its_key(keyed):
    with PoseClient(keyed, api_key=KEY_A) as client:
        assert client.lift(np.asarray(STANDING, np.float32)).joints_3d.shape == (1, 14, 3)
    with PoseClient(keyed, api_key="", retries=3) as client, pytest.raises(ServiceError) as info:
        client.lift(np.asarray(STANDING, np.float32))
    assert info.value.status == 401  # not retried: a key does not appear by waiting


@pytest.mark.slow
def test_no_installed_dependency_has_a_known_vulnerability(tmp_path):
    """pip-audit of this environment (the project itself, editable, left out). Skipped where its
    advisory source cannot answer: `make audit` writes the last result to docs/security/."""
    audit = Path(sys.executable).with_name("pip-audit")
    if not audit.exists():
        missing("pip-audit not installed (the dev extra has it)")
    out = tmp_path / "audit.json"
    command = [str(audit), "--skip-editable", "--progress-spinner", "off", "-f", "json"]
    run = subprocess.run([*command, "-o", str(out)], capture_output=True, text=True, timeout=600)
    if not out.exists():
        pytest.skip(f"pip-audit could not reach its advisory source: {run.stderr[-300:]}")
    dependencies = json.loads(out.read_text())["dependencies"]
    audited = [d for d in dependencies if "skip_reason" not in d]
    if not audited:
        pytest.skip(
            f"the advisory source answered for none of the {len(dependencies)} dependencies "
            "(PyPI's per-release JSON is not reachable from here)"
        )
    found = {d["name"]: [v["id"] for v in d["vulns"]] for d in audited if d["vulns"]}
    assert not found, found
