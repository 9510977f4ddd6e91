"""Speed and memory: `ds3d bench lift`, `ds3d bench retrieval`, `ds3d bench 2d`, `ds3d bench
pipeline`, `ds3d bench memory`. Each measures (ds3d.evaluation.speed) and prints; none gates."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from ds3d.cli.image2d import INFERENCE_OVERRIDE, load_estimator
from ds3d.cli.lift import LIFTER_OVERRIDE, load_lifter
from ds3d.cli.parser import (
    DEFAULT_IMAGE2D,
    add_device_option,
    add_model_options,
    add_set_option,
    add_workers_option,
    load_pipeline,
    write_report,
)


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
    add_device_option(b, "where the 2D stage runs")
    b.add_argument("--threads", type=int, default=1)
    b.add_argument("--repeats", type=int, default=3)
    b.add_argument("--out", type=Path, help="JSON report")
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
    p.add_argument("--images", type=int, default=64, help="different LSP test images")
    p.add_argument("--repeats", type=int, default=2, help="passes through the images")
    p.add_argument(
        "--boxes",
        action="store_true",
        help="each image with its person's box (from its LSP annotation); default: searched",
    )
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, threads=None, device=True)  # --threads: with --workers, the machine's
    add_workers_option(p)
    p.set_defaults(func=bench_pipeline)


def bench_lift(args) -> int:
    from ds3d.evaluation.speed import lift_speed

    start = time.perf_counter()
    lifter = load_lifter(args)
    load_s = time.perf_counter() - start
    sizes = [int(b) for b in args.batch_sizes.split(",")]
    report = {"model": lifter.model_id, "load_s": round(load_s, 2)}
    report |= lift_speed(lifter, sizes, args.repeats)
    for batch, row in report["batches"].items():
        stages = "  ".join(f"{k} {v:.0f} ms" for k, v in row["ms_per_batch"].items())
        print(f"batch {batch:>3}: {row['poses_per_s']:>7} poses/s  {stages}", file=sys.stderr)
    print(f"load {load_s:.1f} s, peak RSS {report['peak_rss_mb']} MB", file=sys.stderr)
    write_report(report, args.out)
    return 0


def bench_retrieval(args) -> int:
    from ds3d.evaluation.speed import retrieval_recall

    nprobes = [int(n) for n in args.nprobe.split(",")]
    report = retrieval_recall(load_lifter(args), args.queries, args.k, nprobes)
    for nprobe, row in report["ivf"].items():
        print(f"nprobe {nprobe}: {row}", file=sys.stderr)
    print(f"flat: {report['flat_ms_per_query']} ms/query (5 sets)", file=sys.stderr)
    write_report(report, args.out)
    return 0


def bench_2d(args) -> int:
    from ds3d.evaluation.speed import estimator_speed

    torch.set_num_threads(args.threads)
    est = load_estimator(args)
    rows = []
    for row in estimator_speed(est, args.repeats):
        print(json.dumps(row), flush=True)
        rows.append(row)
    settings = {
        "threads": args.threads,
        "scales": est.scales(),
        "stride": est.params.stride,
        "scale_choice": est.params.scale_choice,
        "select_stride": est.params.select_stride,
        "coarse_trees": est.params.coarse_trees,
        "step_ms": "summed over the threads (CPU time); total is wall-clock",
    }
    print(json.dumps(settings), file=sys.stderr)
    if args.out is not None:
        write_report({**settings, "rows": rows}, args.out)
    return 0


def bench_pipeline(args) -> int:
    from ds3d.evaluation.speed import pipeline_speed

    pipeline = load_pipeline(args)
    rows = []
    for batch in (int(b) for b in args.batch_sizes.split(",")):
        rows.append(pipeline_speed(pipeline, batch, args.images, args.repeats, args.boxes))
        print(json.dumps(rows[-1]), flush=True)
    report = {
        "device": args.device,
        "threads": args.threads,
        "workers": args.workers,
        "boxes": args.boxes,
        "rows": rows,
    }
    if args.out is not None:
        write_report(report, args.out)
    return 0


def bench_memory(args) -> int:
    from ds3d.evaluation.speed import memory_stream

    pipeline = load_pipeline(args)
    report = memory_stream(
        lambda image: pipeline.estimate([image]), args.images, args.every, args.malloc_trim
    )
    write_report(report, args.out)
    return 0
