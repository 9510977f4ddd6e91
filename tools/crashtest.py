"""Crash test of replicas behind a load balancer: clients send /v1/pose and /v1/lift through it
while one replica is killed with SIGKILL; what every client saw is counted, and the killed
replica's return is timed.

    docker/local_replicas.sh out/replicas &     # two replicas (8001, 8002) behind nginx on 8080
    python -m tools.crashtest http://127.0.0.1:8080 --pid-file out/replicas/replica-8001.pid \\
        --replica http://127.0.0.1:8001 --poses FILE --images DIR --duration 60 --kill-at 15

--clients closed-loop clients of the SDK (ds3d_service.client.AsyncPoseClient, --retries extra
tries: 0 shows what the balancer alone achieves) alternate /v1/pose with one of the images and
/v1/lift with --items poses. At --kill-at seconds the process named by --pid-file is killed; then
the replica's /readyz is polled until it answers 200 again (its supervisor restarts it: compose's
restart policy, or docker/local_replicas.sh). Writes OUT/NAME.json: the outcomes by status, before /
while down / after, the seconds until the replica was ready again, and the requests the restarted
replica served (from its /metrics). Like tools.loadtest, a client of local targets only.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import signal
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import httpx

from ds3d.util.provenance import provenance
from ds3d_service.client import AsyncPoseClient, ServiceError, auth_headers
from tools.loadtest import LOCAL_HOSTS, image_payloads, read_poses

PHASES = ("before", "down", "after")


async def wait_ready(url: str, timeout_s: float, poll_s: float = 0.2) -> float | None:
    """Seconds until GET url/readyz answers 200, or None after timeout_s."""
    t0 = time.perf_counter()
    async with httpx.AsyncClient(base_url=url, timeout=1.0) as probe:
        while (waited := time.perf_counter() - t0) < timeout_s:
            try:
                if (await probe.get("/readyz")).status_code == 200:
                    return waited
            except httpx.TransportError:
                pass
            await asyncio.sleep(poll_s)
    return None


async def api_requests_served(url: str, api_key: str | None) -> int:
    """Requests to /v1/* that the replica at url answered since it started (its /metrics)."""
    from prometheus_client.parser import text_string_to_metric_families

    async with httpx.AsyncClient(
        base_url=url, timeout=5.0, headers=auth_headers(api_key)
    ) as client:
        text = (await client.get("/metrics")).text
    return int(
        sum(
            sample.value
            for family in text_string_to_metric_families(text)
            for sample in family.samples
            if sample.name == "ds3d_requests_total" and sample.labels["route"].startswith("/v1/")
        )
    )


def kill(pid_file: Path) -> int:
    """SIGKILL the process whose id pid_file holds; its id."""
    pid = int(pid_file.read_text())
    os.kill(pid, signal.SIGKILL)
    return pid


async def crash_test(args) -> dict:
    images = image_payloads(args.images, 64)
    joints, visible = read_poses(args.poses)
    outcomes: dict[str, dict[str, int]] = {phase: {} for phase in PHASES}
    killed_at: float | None = None
    ready_after: float | None = None

    def phase(t: float) -> str:
        if killed_at is None or t < killed_at:
            return "before"
        return "down" if ready_after is None or t < killed_at + ready_after else "after"

    async with AsyncPoseClient(
        args.url, timeout=args.timeout, retries=args.retries, api_key=args.api_key
    ) as client:
        t0 = time.perf_counter()
        stop_at = t0 + args.duration

        async def request(rng: random.Random, kind: str) -> None:
            start = time.perf_counter() - t0
            try:
                if kind == "pose":
                    await client.estimate(rng.choice(images)[1])
                else:
                    idx = [rng.randrange(len(joints)) for _ in range(args.items)]
                    await client.lift(joints[idx], visible=visible[idx])
                status = "200"
            except ServiceError as err:
                status = str(err.status)
            except httpx.HTTPError as err:
                status = f"failed:{type(err).__name__}"
            counts = outcomes[phase(start)]
            counts[status] = counts.get(status, 0) + 1

        async def worker(seed: int) -> None:
            rng = random.Random(seed)
            while time.perf_counter() < stop_at:
                await request(rng, rng.choice(("pose", "lift")))

        async def killer() -> None:
            nonlocal killed_at, ready_after
            await asyncio.sleep(args.kill_at)
            killed_pid = kill(args.pid_file)
            killed_at = time.perf_counter() - t0
            print(f"killed replica process {killed_pid} at {killed_at:.1f} s", file=sys.stderr)
            ready_after = await wait_ready(args.replica, args.duration)

        workers = [worker(args.seed + i) for i in range(args.clients)]
        await asyncio.gather(killer(), *workers)

    served = await api_requests_served(args.replica, args.api_key) if ready_after is not None else 0
    every: dict[str, int] = {}
    for counts in outcomes.values():
        for status, n in counts.items():
            every[status] = every.get(status, 0) + n
    return {
        "duration_s": args.duration,
        "clients": args.clients,
        "sdk_retries": args.retries,
        "sent": sum(every.values()),
        "answered_200": every.get("200", 0),
        "answered_503_504": every.get("503", 0) + every.get("504", 0),
        "failed": sum(n for status, n in every.items() if status not in {"200", "503", "504"}),
        "by_status": dict(sorted(every.items())),
        "by_phase": outcomes,
        "killed_at_s": killed_at,
        "ready_again_after_s": ready_after,
        "replica_requests_after_restart": served,
    }


def parse_args(argv):
    p = argparse.ArgumentParser(prog="python -m tools.crashtest", description=__doc__)
    p.add_argument("url", help="the load balancer, e.g. http://127.0.0.1:8080")
    p.add_argument("--pid-file", type=Path, required=True, help="holds the replica's process id")
    p.add_argument("--replica", required=True, help="the killed replica's own URL (its /readyz)")
    p.add_argument("--poses", type=Path, required=True, help="2D poses, `ds3d lift`'s input format")
    p.add_argument("--images", required=True, help="a folder or glob of images for /v1/pose")
    p.add_argument("--duration", type=float, default=60.0, help="seconds of load")
    p.add_argument("--kill-at", type=float, default=15.0, help="seconds into the load")
    p.add_argument("--clients", type=int, default=8)
    p.add_argument("--items", type=int, default=8, help="poses per /v1/lift request")
    p.add_argument("--retries", type=int, default=3, help="the SDK's retries (0: none)")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds per HTTP request")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--api-key", help="sent as Authorization: Bearer KEY (default $DS3D_API_KEY)")
    p.add_argument("--out", type=Path, default=Path("out/crashtest"))
    p.add_argument("--name", default="crashtest")
    args = p.parse_args(argv)
    for url in (args.url, args.replica):
        if urlsplit(url).hostname not in LOCAL_HOSTS:
            p.error(f"{url}: a crash test targets a local deployment (127.0.0.1 or localhost)")
    if not 0 < args.kill_at < args.duration:
        p.error("--kill-at must fall inside --duration")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    result = asyncio.run(crash_test(args))
    result["provenance"] = provenance()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "by_phase"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
