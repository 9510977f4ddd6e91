"""A short soak (tools.soak) against a real `ds3d-serve` process on a small model: a mix of
good and bad requests for a minute, the server's memory and descriptors sampled from its
/metrics. The 30-minute soak and its figures: docs/service-results.md."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import httpx
import pytest

from ds3d_service.allocator import find_jemalloc
from tests.needs import missing
from tools import soak


@pytest.fixture
def server(model_dir, tmp_path):
    """`ds3d-serve` on the small model, a free port; its URL."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    command = [sys.executable, "-m", "ds3d_service", "--port", str(port)]
    command += ["--model-dir", str(model_dir)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            assert process.poll() is None and time.monotonic() < deadline, "server did not start"
            try:
                if httpx.get(f"{url}/readyz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.5)
        yield url
    finally:
        process.terminate()
        process.wait(30)


@pytest.mark.slow
def test_a_short_soak_answers_everything_and_leaks_no_descriptors(server, load_inputs, tmp_path):
    poses, images = load_inputs
    args = ["--duration", "60", "--warmup", "20", "--sample-every", "3", "--clients", "3"]
    args += ["--poses", str(poses), "--images", str(images), "--out", str(tmp_path / "out")]
    assert soak.main([server, *args]) == 0
    result = json.loads((tmp_path / "out" / "soak.json").read_text())
    assert (tmp_path / "out" / "soak.png").stat().st_size > 10_000
    by_kind = result["status_by_kind"]
    # no failure of the service: a 504 is its answer when this busy machine delays a batch
    # past the deadline, but no 500 and no dropped connection
    for kind in ("pose", "lift"):
        statuses = by_kind[kind]
        assert set(statuses) <= {"200", "504"}, by_kind
        assert statuses.get("200", 0) >= 0.8 * sum(statuses.values()), by_kind
    assert set(by_kind["bad"]) == {"422"}, by_kind  # every bad request refused, none crashed
    assert result["health_after"] == {"/healthz": 200, "/readyz": 200}
    memory = result["memory"]
    assert len(result["usage"]) >= 8 and memory["rss_mb_after_warmup"] > 100
    # every request's connection and upload closed: no descriptor left open per request
    assert memory["open_fds_end"] <= memory["open_fds_after_warmup"] + 4, memory


@pytest.mark.slow  # its server starts in about 12 s
def test_the_service_runs_under_jemalloc_where_installed(server):
    if find_jemalloc() is None:
        missing("jemalloc not installed (Debian: apt-get install libjemalloc2)")
    assert 'ds3d_allocator_info{name="jemalloc"} 1.0' in httpx.get(f"{server}/metrics").text
