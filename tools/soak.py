"""Soak test of a local ds3d service: a mix of requests for a long time, and the server's memory
and open files over it, read from its /metrics.

    python -m tools.soak http://127.0.0.1:8000 --duration 1800 --poses FILE --images DIR

--clients closed-loop clients each send, in turn by --mix weights, /v1/pose with one of the
images, /v1/lift with --items poses, and a bad request (text as an image, a pose of three
joints, a box outside its image). Every --sample-every seconds the resident memory of the server
and its worker processes (ds3d_resident_memory_bytes) and the server's open file descriptors
(process_open_fds). Writes
OUT/NAME.json (the samples, counts by kind and status, latency, and the memory's drift after the
warm-up and its trend over the last third) and OUT/NAME.png (memory, descriptors and latency over
time). Like tools.loadtest, a client of local targets only.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np

from ds3d.util.provenance import provenance
from ds3d_service.client import auth_headers
from tools.loadtest import (
    LOCAL_HOSTS,
    Sample,
    image_payloads,
    lift_payloads,
    read_poses,
    server_metrics,
)

KINDS = ("pose", "lift", "bad")


@dataclass
class Usage:
    at_s: float  # since the soak began
    rss_mb: float
    open_fds: int


async def server_usage(client: httpx.AsyncClient) -> tuple[float, int]:
    """The server's (resident memory in MB of it and its worker processes, open file
    descriptors) from its /metrics (process_resident_memory_bytes, the server's alone, from a
    server without ds3d_resident_memory_bytes)."""
    values = await server_metrics(client)
    try:
        memory = values.get("ds3d_resident_memory_bytes", values["process_resident_memory_bytes"])
        return memory / 2**20, int(values["process_open_fds"])
    except KeyError:
        raise SystemExit("the server's /metrics has no process_* metrics (not Linux?)") from None


def bad_requests(image: bytes) -> list[tuple[str, dict]]:
    """(path, httpx.post keyword arguments) of requests the service must refuse with a 4xx."""
    three_joints = {"items": [{"joints_2d": [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]}]}
    outside = {"bbox": "[90000, 90000, 90010, 90010]"}
    return [
        ("/v1/pose", {"files": {"image": ("notes.jpg", b"not an image at all")}}),
        ("/v1/lift", {"json": three_joints}),
        ("/v1/pose", {"files": {"image": ("photo.jpg", image)}, "data": outside}),
    ]


def drift(usage: list[Usage], warmup_s: float) -> dict:
    """RSS after the warm-up against the end (% of the first), and the trend after the warm-up:
    the median of each third (robust to the allocator's swings; the last against the middle in
    %), and the last third's linear fit: its slope (MB per minute) and change over the third (%
    of its start)."""
    after = [u for u in usage if u.at_s >= warmup_s]
    if len(after) < 3:
        return {}
    t = np.array([u.at_s for u in after])
    rss = np.array([u.rss_mb for u in after])
    last = t >= t[0] + 2 * (t[-1] - t[0]) / 3
    slope, _ = np.polyfit(t[last] / 60.0, rss[last], 1)
    span_min = (t[last][-1] - t[last][0]) / 60.0
    third = np.minimum(((t - t[0]) * 3 // max(t[-1] - t[0], 1e-9)).astype(int), 2)
    medians = [float(np.median(rss[third == k])) for k in range(3)]
    return {
        "warmup_s": warmup_s,
        "rss_mb_after_warmup": float(rss[0]),
        "rss_mb_end": float(rss[-1]),
        "rss_mb_max": float(rss.max()),
        "drift_pct": float(100 * (rss[-1] - rss[0]) / rss[0]),
        "rss_mb_median_by_third": medians,
        "last_vs_middle_third_pct": float(100 * (medians[2] - medians[1]) / medians[1]),
        "last_third_slope_mb_per_min": float(slope),
        "last_third_change_pct": float(100 * slope * span_min / rss[last][0]),
        "open_fds_after_warmup": after[0].open_fds,
        "open_fds_end": after[-1].open_fds,
    }


async def soak(args) -> tuple[dict, dict[str, list[Sample]]]:
    images = image_payloads(args.images, 64)
    lifts = lift_payloads(read_poses(args.poses), args.items, 256, args.seed)
    bad = bad_requests(images[0][1])
    weights = [args.mix[k] for k in KINDS]
    samples: dict[str, list[Sample]] = {k: [] for k in KINDS}
    usage: list[Usage] = []
    async with httpx.AsyncClient(
        base_url=args.url, timeout=args.timeout, headers=auth_headers(args.api_key)
    ) as client:
        t0 = time.perf_counter()
        stop_at = t0 + args.duration

        async def request(kind: str, rng: random.Random) -> None:
            kwargs: dict[str, Any]  # httpx.AsyncClient.post's keyword arguments
            if kind == "pose":
                name, data = rng.choice(images)
                path, kwargs = "/v1/pose", {"files": {"image": (name, data)}}
            elif kind == "lift":
                path, kwargs = "/v1/lift", {"json": rng.choice(lifts)}
            else:
                path, kwargs = rng.choice(bad)
            start = time.perf_counter()
            try:
                status = str((await client.post(path, **kwargs)).status_code)
            except httpx.HTTPError as err:
                status = f"error:{type(err).__name__}"
            samples[kind].append(Sample(start - t0, time.perf_counter() - start, status))

        async def worker(seed: int) -> None:
            rng = random.Random(seed)
            while time.perf_counter() < stop_at:
                await request(rng.choices(KINDS, weights)[0], rng)

        async def sampler() -> None:
            while True:
                rss, fds = await server_usage(client)
                usage.append(Usage(time.perf_counter() - t0, rss, fds))
                if time.perf_counter() >= stop_at:
                    return
                await asyncio.sleep(min(args.sample_every, max(stop_at - time.perf_counter(), 0)))

        workers = [worker(args.seed + 1 + i) for i in range(args.clients)]
        await asyncio.gather(sampler(), *workers)
        health = {path: (await client.get(path)).status_code for path in ("/healthz", "/readyz")}
    return report(args, samples, usage, health), samples


def report(args, samples: dict[str, list[Sample]], usage: list[Usage], health: dict) -> dict:
    def counts(kind_samples):
        out: dict[str, int] = {}
        for s in kind_samples:
            out[s.status] = out.get(s.status, 0) + 1
        return dict(sorted(out.items()))

    def p99_ms(kind_samples):
        ok = [s.latency_s for s in kind_samples if s.status == "200"]
        return float(np.percentile(ok, 99) * 1000) if ok else None

    everything = [s for k in KINDS for s in samples[k]]
    return {
        "duration_s": args.duration,
        "clients": args.clients,
        "mix": args.mix,
        "items_per_lift": args.items,
        "requests": len(everything),
        "status_by_kind": {k: counts(samples[k]) for k in KINDS},
        "server_errors": sum(s.status.startswith(("5", "error")) for s in everything),
        "p99_ms_ok_by_kind": {k: p99_ms(samples[k]) for k in KINDS},
        "health_after": health,
        "memory": drift(usage, args.warmup),
        "usage": [[round(u.at_s, 1), round(u.rss_mb, 1), u.open_fds] for u in usage],
    }


def plot(result: dict, samples: dict[str, list[Sample]], path: Path) -> None:
    """Server memory and descriptors over the soak (top), each request's latency (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    at, rss, fds = np.array(result["usage"], dtype=float).T
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    top.plot(at / 60, rss, color="tab:blue")
    top.set_ylabel("server RSS (MB)", color="tab:blue")
    twin = top.twinx()
    twin.plot(at / 60, fds, color="tab:orange", lw=1)
    twin.set_ylabel("open fds", color="tab:orange")
    memory = result["memory"]
    if memory:
        top.axvline(memory["warmup_s"] / 60, color="0.6", ls="--", lw=1)
        top.set_title(
            f"RSS after warm-up {memory['drift_pct']:+.1f} %, last third "
            f"{memory['last_third_slope_mb_per_min']:+.2f} MB/min",
            fontsize=9,
        )
    for kind in KINDS:
        points = [(s.start_s / 60, s.latency_s * 1000) for s in samples[kind]]
        if points:
            bottom.scatter(*zip(*points, strict=True), s=2, label=f"{kind} ({len(points)})")
    bottom.set_yscale("log")
    bottom.set_ylabel("latency (ms)")
    bottom.set_xlabel("minutes")
    bottom.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parse_mix(text: str) -> dict[str, float]:
    """'pose=1,lift=4,bad=1' -> weights of KINDS."""
    try:
        mix = {k: float(v) for k, v in (part.split("=") for part in text.split(","))}
    except ValueError:
        raise argparse.ArgumentTypeError(f"want KIND=WEIGHT,... got {text!r}") from None
    if set(mix) - set(KINDS) or not any(mix.values()):
        raise argparse.ArgumentTypeError(f"kinds are {KINDS}, with a positive weight")
    return {k: mix.get(k, 0.0) for k in KINDS}


def parse_args(argv):
    p = argparse.ArgumentParser(prog="python -m tools.soak", description=__doc__.split("\n")[0])
    p.add_argument("url", help="base URL of a local service, e.g. http://127.0.0.1:8000")
    p.add_argument("--duration", type=float, default=1800.0, help="seconds (max 86400)")
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--mix", type=parse_mix, default=parse_mix("pose=2,lift=2,bad=1"))
    p.add_argument("--items", type=int, default=8, help="poses per /v1/lift request")
    p.add_argument("--poses", type=Path, required=True, metavar="FILE", help="as tools.loadtest")
    p.add_argument("--images", required=True, metavar="DIR_OR_GLOB", help="as tools.loadtest")
    p.add_argument("--sample-every", type=float, default=10.0, help="seconds between samples")
    p.add_argument("--warmup", type=float, default=120.0, help="seconds before the drift counts")
    p.add_argument("--timeout", type=float, default=30.0, help="client timeout per request (s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--api-key", help="sent as Authorization: Bearer KEY (default $DS3D_API_KEY)")
    p.add_argument("--out", type=Path, default=Path("out/soak"), help="folder for JSON + PNG")
    p.add_argument("--name", default="soak", help="file stem")
    args = p.parse_args(argv)
    if urlsplit(args.url).hostname not in LOCAL_HOSTS:
        p.error("only local targets (127.0.0.1, localhost, ::1) are allowed")
    if not 0 < args.duration <= 86400 or args.clients < 1 or args.sample_every <= 0:
        p.error("need 0 < duration <= 86400, clients >= 1, sample-every > 0")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    result, samples = asyncio.run(soak(args))
    result["provenance"] = provenance()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    plot(result, samples, args.out / f"{args.name}.png")
    summary = {k: v for k, v in result.items() if k != "usage"}
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
