"""Speed and memory: `ds3d bench lift`, `ds3d bench retrieval`, `ds3d bench 2d`, `ds3d bench
pipeline`, `ds3d bench memory`. Each measures and prints; none gates."""

from __future__ import annotations

import json
import os
import resource
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from ds3d.cli.image2d import INFERENCE_OVERRIDE, load_estimator
from ds3d.cli.lift import LIFTER_OVERRIDE, load_lifter
from ds3d.cli.parser import DEFAULT_IMAGE2D, add_model_options, add_set_option, write_report
from ds3d.cli.pipeline import add_workers_option, load_pipeline
from ds3d.skeleton import SET_NAMES
from ds3d.util.memory import glibc_heap_mb, loaded_allocator, malloc_trim, resident_mb
from ds3d.util.progress import progress

# The environment that changes how memory is allocated, recorded in `bench memory`'s report.
MEMORY_ENV_PREFIXES = ("MALLOC_", "LD_PRELOAD", "ONEDNN_", "DNNL_")


def register(commands, evals, benches) -> None:
    p = benches.add_parser("retrieval", help="IVF recall@K against the exact (flat) index")
    p.add_argument("--queries", type=int, default=256)
    p.add_argument("--k", type=int, default=256)
    p.add_argument("--nprobe", default="8,16,32")
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, threads=None, device=True)
    p.set_defaults(func=bench_retrieval)

    p = benches.add_parser("lift", help="poses per second and time per stage")
    p.add_argument("--batch-sizes", default="1,16,64")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, threads=None, device=True)
    add_set_option(p, LIFTER_OVERRIDE)
    p.set_defaults(func=bench_lift)

    b = benches.add_parser("2d", help="images/s of the 2D stage, time per step")
    b.add_argument("--model", type=Path, default=DEFAULT_IMAGE2D)
    b.add_argument("--threads", type=int, default=1)
    b.add_argument("--repeats", type=int, default=3)
    add_set_option(b, INFERENCE_OVERRIDE)
    b.set_defaults(func=bench_2d)

    p = benches.add_parser("memory", help="resident memory over a stream of images of all sizes")
    p.add_argument("--images", type=int, default=360, help="LSP test images, one at a time")
    p.add_argument("--every", type=int, default=40, help="report every N images")
    p.add_argument("--malloc-trim", action="store_true", help="glibc malloc_trim after each image")
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p)
    p.set_defaults(func=bench_memory)

    p = benches.add_parser("pipeline", help="images/s end to end and the time of each stage")
    p.add_argument("--batch-sizes", default="1,16")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument(
        "--boxes",
        action="store_true",
        help="each image with its person's box (from its LSP annotation); default: searched",
    )
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, device=True)
    add_workers_option(p)
    p.set_defaults(func=bench_pipeline)


def bench_images(n: int, size: tuple[int, int] | None = None) -> list[np.ndarray]:
    """n LSP test images (resized to size = (w, h) if given), or noise of LSP's typical size
    where the dataset is absent."""
    from ds3d.data.lsp import load_lsp
    from ds3d.io.images import read_image
    from ds3d.util.paths import data_root

    if (data_root() / "lsp" / "joints.mat").is_file():
        images = [read_image(p) for p in load_lsp(split="test").image_paths[:n]]
    else:
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (175, 110, 3), dtype=np.uint8) for _ in range(n)]
    if size is not None:
        images = [cv2.resize(im, size, interpolation=cv2.INTER_LINEAR) for im in images]
    return images


def bench_boxes(n: int) -> list[np.ndarray]:
    """The person boxes (x0, y0, x1, y1) px of bench_images(n), from the LSP annotations."""
    from ds3d.boxes import person_boxes
    from ds3d.data.lsp import load_lsp

    return list(person_boxes(load_lsp(split="test").joints[:n]).astype(np.float32))


def benchmark_poses(lifter, count: int, seed: int = 0) -> np.ndarray:
    """Plausible 2D inputs without any dataset: database poses seen from random virtual views,
    scaled to ~400 px tall in a 1000 x 1000 image. Returns (count, 14, 2) float32 px."""
    rng = np.random.default_rng(seed)
    db = lifter.database
    ids = torch.from_numpy(rng.integers(0, len(db), count))
    poses = db.candidates(ids.to(db.poses.device)).cpu().numpy()
    return (poses[..., :2] * 0.22 + 500).astype(np.float32)


def bench_lift(args) -> int:
    start = time.perf_counter()
    lifter = load_lifter(args)
    load_s = time.perf_counter() - start
    report = {
        "model": lifter.model_id,
        "device": str(lifter.device),
        "threads": torch.get_num_threads(),
        "load_s": round(load_s, 2),
        "batches": {},
    }
    for batch in (int(b) for b in args.batch_sizes.split(",")):
        inputs = benchmark_poses(lifter, batch * (args.repeats + 1))
        lifter.lift(inputs[:batch])  # warm-up
        stages: dict[str, float] = {}
        elapsed = 0.0
        with progress(total=batch * args.repeats, desc=f"batch {batch}", unit="pose") as bar:
            for r in range(1, args.repeats + 1):
                t = time.perf_counter()
                result = lifter.lift(inputs[r * batch : (r + 1) * batch])
                elapsed += time.perf_counter() - t
                for stage, ms in result.timings_ms.items():
                    stages[stage] = stages.get(stage, 0.0) + ms / args.repeats
                bar.update(batch)
        report["batches"][batch] = {
            "poses_per_s": round(batch * args.repeats / elapsed, 1),
            "ms_per_batch": {k: round(v, 1) for k, v in stages.items()},
        }
        print(
            f"batch {batch:>3}: {report['batches'][batch]['poses_per_s']:>7} poses/s  "
            + "  ".join(f"{k} {v:.0f} ms" for k, v in stages.items()),
            file=sys.stderr,
        )
    report["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    print(f"load {load_s:.1f} s, peak RSS {report['peak_rss_mb']} MB", file=sys.stderr)
    write_report(report, args.out)
    return 0


def bench_retrieval(args) -> int:
    """Recall@k of the default IVF index against an exact flat index, per set, and the time per
    query of each, on plausible queries (benchmark_poses plus 5 px of noise)."""
    from ds3d.mocap.retrieval import IndexConfig, PoseRetriever

    lifter = load_lifter(args)
    rng = np.random.default_rng(1)
    noisy = benchmark_poses(lifter, args.queries) + rng.normal(0, 5, (args.queries, 14, 2))
    queries = torch.from_numpy(noisy.astype(np.float32))
    exact = PoseRetriever(lifter.database, IndexConfig(kind="flat", storage="f32"), cache=False)
    nprobes = [int(n) for n in args.nprobe.split(",")]
    with progress(total=args.queries * (1 + len(nprobes)), desc="retrieval", unit="query") as bar:
        start = time.perf_counter()
        truth = exact.search(queries, args.k)
        report = {
            "k": args.k,
            "queries": args.queries,
            "flat_ms_per_query": round(1000 * (time.perf_counter() - start) / args.queries, 2),
            "ivf": {},
        }
        del exact
        bar.update(args.queries)
        for nprobe in nprobes:
            start = time.perf_counter()
            found = lifter.retriever.search(queries, args.k, nprobe)
            elapsed = time.perf_counter() - start
            bar.update(args.queries)
            recall = {
                name: float(
                    np.mean(
                        [
                            len(set(f.tolist()) & set(t.tolist())) / args.k
                            for f, t in zip(found[:, s], truth[:, s], strict=True)
                        ]
                    )
                )
                for s, name in enumerate(SET_NAMES)
            }
            report["ivf"][nprobe] = {
                "ms_per_query": round(1000 * elapsed / args.queries, 2),
                "recall": {k: round(v, 3) for k, v in recall.items()},
            }
            bar.write(f"nprobe {nprobe}: {report['ivf'][nprobe]}", file=sys.stderr)
    print(f"flat: {report['flat_ms_per_query']} ms/query (5 sets)", file=sys.stderr)
    write_report(report, args.out)
    return 0


def bench_2d(args) -> int:
    torch.set_num_threads(args.threads)
    est = load_estimator(args)
    rows = []
    for label, size in (("lsp-sized", None), ("640x480", (640, 480))):
        images = bench_images(16, size)
        for batch in (1, 16):
            est.estimate(images[:batch])  # warm-up
            steps = {"features": 0.0, "traversal": 0.0, "jointnet": 0.0, "psm": 0.0, "total": 0.0}
            with progress(total=args.repeats * batch, desc=f"{label} x{batch}", unit="img") as bar:
                for _ in range(args.repeats):
                    res = est.estimate(images[:batch])
                    for k in steps:
                        steps[k] += res.timings[k]
                    bar.update(batch)
            n = args.repeats * batch
            rows.append(
                {
                    "image": label,
                    "shape": list(images[0].shape[:2]),
                    "batch": batch,
                    "images_per_s": round(n / steps["total"], 2),
                    "ms_per_image": {k: round(1000 * v / n, 1) for k, v in steps.items()},
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    print(
        json.dumps(
            {
                "threads": args.threads,
                "scales": est.scales(),
                "stride": est.params.stride,
                "scale_choice": est.params.scale_choice,
                "select_stride": est.params.select_stride,
                "coarse_trees": est.params.coarse_trees,
                "step_ms": "summed over the threads (CPU time); total is wall-clock",
            }
        ),
        file=sys.stderr,
    )
    return 0


def bench_pipeline(args) -> int:
    pipeline = load_pipeline(args)
    sizes = [int(b) for b in args.batch_sizes.split(",")]
    images = bench_images(max(sizes))
    boxes = bench_boxes(len(images)) if args.boxes else None
    rows = []
    for batch in sizes:
        bboxes = None if boxes is None else boxes[:batch]
        pipeline.estimate(images[:batch], bboxes)  # warm-up
        stages: dict[str, float] = {}
        with progress(total=args.repeats * batch, desc=f"batch {batch}", unit="img") as bar:
            for _ in range(args.repeats):
                res = pipeline.estimate(images[:batch], bboxes)
                for stage, ms in res.timings_ms.items():
                    stages[stage] = stages.get(stage, 0.0) + ms
                bar.update(batch)
        n = args.repeats * batch
        rows.append(
            {
                "batch": batch,
                "images_per_s": round(1000 * n / stages["total"], 2),
                "ms_per_image": {k: round(v / n, 1) for k, v in stages.items()},
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    report = {
        "device": args.device,
        "threads": args.threads,
        "workers": args.workers,
        "boxes": args.boxes,
        "iterations": pipeline.config.iterations,
        "rows": rows,
    }
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def bench_memory(args) -> int:
    """The pipeline on --images LSP test images one at a time, as a service sees them (each a new
    size): the resident memory every --every images and its growth from the first report (after
    warm-up) to the end. Run it under each allocator (LD_PRELOAD, MALLOC_* env vars)."""
    from ds3d.data.lsp import load_lsp
    from ds3d.io.images import read_image

    pipeline = load_pipeline(args)
    paths = load_lsp(split="test").image_paths[: args.images]
    rows = []
    start = time.perf_counter()
    for i, path in enumerate(progress(paths, desc="images", unit="img"), start=1):
        pipeline.estimate([read_image(path)])
        if args.malloc_trim:
            malloc_trim()
        if i % args.every == 0 or i == len(paths):
            rows.append({"images": i, "rss_mb": round(resident_mb(), 1)} | (glibc_heap_mb() or {}))
    seconds = time.perf_counter() - start
    first, last = rows[0]["rss_mb"], rows[-1]["rss_mb"]
    report = {
        "allocator": loaded_allocator(),
        "malloc_trim": args.malloc_trim,
        "env": {k: v for k, v in os.environ.items() if k.startswith(MEMORY_ENV_PREFIXES)},
        "rss_mb": rows,
        "growth_pct": round(100 * (last - first) / first, 1),
        "s_per_image": round(seconds / len(paths), 3),
    }
    write_report(report, args.out)
    return 0
