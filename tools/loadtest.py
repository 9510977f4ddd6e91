"""Load test of a local ds3d service.

    python -m tools.loadtest http://127.0.0.1:8000 --mode closed --concurrency 16 --duration 30
    python -m tools.loadtest http://127.0.0.1:8000 --mode open --rate 50 --duration 30
    python -m tools.loadtest URL --endpoint pose --images DIR_OR_GLOB ...

Closed loop: N workers, each sends its next request when the previous one is answered.
Open loop: requests start at a fixed rate whether or not earlier ones were answered (this is how
overload shows). /v1/lift payloads are random poses of the --poses file (`ds3d lift`'s input
format; docker/loadtest_matrix.sh writes LSP's annotations to one); /v1/pose payloads are image
files, those of the folder or those matching the glob that --images gives. The tool is a client:
it imports nothing of the library.
Raw httpx, no retries: every status is counted as the service gave it. A closed-loop worker told
429 (its caller over its share) waits the Retry-After it was given before its next request, as
HTTP asks and the SDK does; without that, a refused worker's instant resends take the cores of
this machine from the service it measures. Prints and writes JSON
(throughput, latency percentiles, counts by status) and a PNG of latency over time.
Bounded: at most --max-requests requests and --duration seconds (plus the last answers); only
local targets (127.0.0.1, localhost, ::1).
"""

from __future__ import annotations

import argparse
import asyncio
import glob
import json
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np

from ds3d.util.provenance import provenance
from ds3d_service.client import auth_headers

LOCAL_HOSTS = {"127.0.0.1", "localhost", "::1"}
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".webp"}


@dataclass
class Sample:
    start_s: float  # since the test began
    latency_s: float
    status: str  # "200", "503", ... or "error:<exception>"


def lift_payloads(poses: tuple[np.ndarray, np.ndarray], items: int, count: int, seed: int):
    """`count` JSON bodies of `items` random poses each. poses: joints_2d (N, 14, 2) pixels,
    visible (N, 14) bool."""
    xy, visible = poses
    rng = random.Random(seed)
    bodies = []
    for _ in range(count):
        idx = [rng.randrange(len(xy)) for _ in range(items)]
        bodies.append(
            {"items": [{"joints_2d": xy[i].tolist(), "visible": visible[i].tolist()} for i in idx]}
        )
    return bodies


def read_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """2D poses from a JSON file in `ds3d lift`'s input format: {"joints_2d": [[[x, y] x 14],
    ...], "visible": optional [[bool x 14], ...]} -> joints_2d (N, 14, 2) float32 px, visible
    (N, 14) bool (all true without "visible")."""
    try:
        data = json.loads(Path(path).read_text())
        xy = np.asarray(data["joints_2d"], dtype=np.float32)
        visible = np.asarray(data.get("visible", np.ones(xy.shape[:2])), dtype=bool)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"--poses {path}: {exc}") from None
    if xy.ndim != 3 or xy.shape[1:] != (14, 2) or visible.shape != xy.shape[:2] or not len(xy):
        raise SystemExit(f"--poses {path}: need joints_2d of shape (N, 14, 2), visible (N, 14)")
    return xy, visible


def image_files(source: str | Path) -> list[Path]:
    """The image files (by suffix) in the folder `source`, or matching the glob pattern `source`
    ("**" descends into folders), sorted."""
    folder = Path(source)
    found = (
        folder.iterdir() if folder.is_dir() else map(Path, glob.glob(str(source), recursive=True))
    )
    return sorted(p for p in found if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def image_payloads(source: str | Path, limit: int) -> list[tuple[str, bytes]]:
    """(file name, bytes) of the first `limit` image files of `source` (see image_files)."""
    files = image_files(source)[:limit]
    if not files:
        raise SystemExit(f"no images in {source}")
    return [(p.name, p.read_bytes()) for p in files]


def summarize(
    samples: list[Sample], window_s: float, elapsed_s: float, deadline_s: float | None = None
) -> dict:
    """Throughput: answers (all, and 200s) that ended inside the load window [0, window_s], per
    second (the answers still arriving after the window, e.g. 504s, do not dilute it).
    Latency percentiles (ms) of the 200s and of all answers, counts by status over the whole run;
    with a deadline, how many answers came later than it."""
    counts: dict[str, int] = {}
    for s in samples:
        counts[s.status] = counts.get(s.status, 0) + 1
    in_window = [s for s in samples if s.start_s + s.latency_s <= window_s]

    def pct(values):
        if not values:
            return None
        v = np.asarray(values) * 1000.0
        return {
            "p50": float(np.percentile(v, 50)),
            "p95": float(np.percentile(v, 95)),
            "p99": float(np.percentile(v, 99)),
            "max": float(v.max()),
        }

    ok = [s.latency_s for s in samples if s.status == "200"]
    return {
        "requests": len(samples),
        "window_s": window_s,
        "elapsed_s": elapsed_s,
        "throughput_rps": len(in_window) / window_s,
        "ok_rps": sum(s.status == "200" for s in in_window) / window_s,
        "latency_ms_ok": pct(ok),
        "latency_ms_all": pct([s.latency_s for s in samples]),
        "max_latency_ms_by_status": {
            st: 1000.0 * max(s.latency_s for s in samples if s.status == st) for st in counts
        },
        "status_counts": dict(sorted(counts.items())),
        "deadline_s": deadline_s,
        "over_deadline": None
        if deadline_s is None
        else sum(s.latency_s > deadline_s for s in samples),
    }


def plot(samples: list[Sample], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for status in sorted({s.status for s in samples}):
        pts = [(s.start_s, s.latency_s * 1000) for s in samples if s.status == status]
        starts, latencies = zip(*pts, strict=True)
        ax.scatter(starts, latencies, s=4, label=f"{status} ({len(pts)})")
    ax.set_xlabel("request start (s)")
    ax.set_ylabel("latency (ms)")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


class Runner:
    def __init__(self, client: httpx.AsyncClient, endpoint: str, payloads: list, t0: float):
        self.client, self.endpoint, self.payloads, self.t0 = client, endpoint, payloads, t0
        self.samples: list[Sample] = []
        self._next = 0

    async def one(self) -> float:
        """Send the next request and record its answer; the seconds a 429 asks to wait (else 0)."""
        payload = self.payloads[self._next % len(self.payloads)]
        self._next += 1
        start = time.perf_counter()
        try:
            if self.endpoint == "lift":
                resp = await self.client.post("/v1/lift", json=payload)
            else:
                name, data = payload
                resp = await self.client.post("/v1/pose", files={"image": (name, data)})
            status = str(resp.status_code)
        except httpx.HTTPError as e:
            status = f"error:{type(e).__name__}"
            resp = None
        end = time.perf_counter()
        self.samples.append(Sample(start - self.t0, end - start, status))
        if resp is None or status != "429":
            return 0.0
        return float(resp.headers.get("retry-after", 1))


async def server_metrics(client: httpx.AsyncClient, queue: str | None = None) -> dict[str, float]:
    """The server's /metrics samples (a replica's own, when behind a load balancer), by name;
    with `queue`, of those labelled by a queue only that queue's."""
    from prometheus_client.parser import text_string_to_metric_families

    values = {}
    for family in text_string_to_metric_families((await client.get("/metrics")).text):
        for sample in family.samples:
            if queue is None or sample.labels.get("queue", queue) == queue:
                values[sample.name] = sample.value
    return values


async def batch_totals(client: httpx.AsyncClient, queue: str) -> tuple[float, float, float]:
    """The server's (items batched, batches, items dropped for their deadline) so far."""
    values = await server_metrics(client, queue)
    names = ("ds3d_batch_size_sum", "ds3d_batch_size_count", "ds3d_deadline_dropped_items_total")
    items, batches, dropped = (values.get(name, 0.0) for name in names)
    return items, batches, dropped


async def closed_loop(runner: Runner, concurrency: int, duration_s: float, max_requests: int):
    stop_at = runner.t0 + duration_s
    budget = iter(range(max_requests))

    async def worker():
        while time.perf_counter() < stop_at and next(budget, None) is not None:
            await asyncio.sleep(min(await runner.one(), max(stop_at - time.perf_counter(), 0)))

    await asyncio.gather(*(worker() for _ in range(concurrency)))


async def open_loop(runner: Runner, rate: float, duration_s: float, max_requests: int):
    count = min(max_requests, int(rate * duration_s))
    tasks = []
    for i in range(count):
        delay = runner.t0 + i / rate - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        tasks.append(asyncio.create_task(runner.one()))
    await asyncio.gather(*tasks)


async def run(args) -> tuple[dict, list[Sample]]:
    if args.endpoint == "lift":
        if args.poses is None:
            raise SystemExit("--endpoint lift needs --poses FILE")
        payloads = lift_payloads(read_poses(args.poses), args.items, 512, args.seed)
    else:
        if args.images is None:
            raise SystemExit("--endpoint pose needs --images DIR_OR_GLOB")
        payloads = image_payloads(args.images, 256)
    limits = httpx.Limits(max_connections=args.max_connections, max_keepalive_connections=64)
    async with httpx.AsyncClient(
        base_url=args.url, timeout=args.timeout, limits=limits, headers=auth_headers(args.api_key)
    ) as client:
        batches_before = await batch_totals(client, args.endpoint)
        runner = Runner(client, args.endpoint, payloads, time.perf_counter())
        if args.mode == "closed":
            await closed_loop(runner, args.concurrency, args.duration, args.max_requests)
        else:
            await open_loop(runner, args.rate, args.duration, args.max_requests)
        elapsed = time.perf_counter() - runner.t0
        result = summarize(runner.samples, args.duration, elapsed, args.deadline)
        after = {path: (await client.get(path)).status_code for path in ("/healthz", "/readyz")}
        batches_after = await batch_totals(client, args.endpoint)
        # the server's and its worker processes' (ds3d_resident_memory_bytes), where it says
        resident = (await server_metrics(client)).get("ds3d_resident_memory_bytes")
    items, batches, dropped = (a - b for a, b in zip(batches_after, batches_before, strict=True))
    result.update(
        endpoint=args.endpoint,
        mode=args.mode,
        concurrency=args.concurrency if args.mode == "closed" else None,
        rate=args.rate if args.mode == "open" else None,
        items_per_request=args.items if args.endpoint == "lift" else 1,
        health_after=after,
        server_batches=batches,
        server_mean_batch_size=items / batches if batches else None,
        server_deadline_dropped=dropped,
        server_resident_mb=None if resident is None else round(resident / 2**20, 1),
    )
    return result, runner.samples


def parse_args(argv):
    p = argparse.ArgumentParser(prog="python -m tools.loadtest", description=__doc__.split("\n")[0])
    p.add_argument("url", help="base URL of a local service, e.g. http://127.0.0.1:8000")
    p.add_argument("--endpoint", choices=("lift", "pose"), default="lift")
    p.add_argument("--mode", choices=("closed", "open"), default="closed")
    p.add_argument("--concurrency", type=int, default=4, help="closed loop: requests in flight")
    p.add_argument("--rate", type=float, default=10.0, help="open loop: requests per second")
    p.add_argument("--duration", type=float, default=10.0, help="seconds of load (max 600)")
    p.add_argument("--max-requests", type=int, default=100_000)
    p.add_argument("--items", type=int, default=1, help="lift: poses per request")
    p.add_argument(
        "--poses",
        type=Path,
        metavar="FILE",
        help='lift: 2D poses, JSON as `ds3d lift` reads it ({"joints_2d": [...], "visible": ...})',
    )
    p.add_argument(
        "--images",
        metavar="DIR_OR_GLOB",
        help="pose: a folder of images, or a glob of image files (quoted, e.g. 'photos/*.jpg')",
    )
    p.add_argument("--timeout", type=float, default=30.0, help="client timeout per request (s)")
    p.add_argument("--max-connections", type=int, default=512)
    p.add_argument("--deadline", type=float, help="count answers slower than this (s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--api-key", help="sent as Authorization: Bearer KEY (default $DS3D_API_KEY)")
    p.add_argument("--out", type=Path, default=Path("out/loadtest"), help="folder for JSON + PNG")
    p.add_argument("--name", help="file stem (default: endpoint_mode_N)")
    args = p.parse_args(argv)
    if urlsplit(args.url).hostname not in LOCAL_HOSTS:
        p.error("only local targets (127.0.0.1, localhost, ::1) are allowed")
    if not 0 < args.duration <= 600 or args.concurrency < 1 or args.rate <= 0:
        p.error("need 0 < duration <= 600, concurrency >= 1, rate > 0")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    result, samples = asyncio.run(run(args))
    result["provenance"] = provenance()
    load = f"c{args.concurrency}" if args.mode == "closed" else f"r{args.rate:g}"
    stem = args.name or f"{args.endpoint}_{args.mode}_{load}"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{stem}.json").write_text(json.dumps(result, indent=2))
    if samples:
        plot(samples, f"{args.endpoint} {args.mode} {load}", args.out / f"{stem}.png")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
