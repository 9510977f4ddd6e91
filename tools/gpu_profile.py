"""Where the time goes on a GPU: torch.profiler over Pipeline.estimate (LSP test images, people
searched) and Lifter.lift, after a warm-up of each; the ops by self CUDA time and by self CPU
time (kernel launches show there), and the stages' own timings. One of tools.gpu_check's steps.

    python -m tools.gpu_profile --out profile.json [--device cuda] [--batch 64] [--poses 1024]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from ds3d.evaluation.speed import bench_images, benchmark_poses
from ds3d.pipeline import Pipeline

ROWS = 25


def profiled(run, device: str) -> dict:
    """run() once to warm up, then once under the profiler -> its op tables and result's timings."""
    run()
    activities = [ProfilerActivity.CPU]
    if device.startswith("cuda"):
        activities.append(ProfilerActivity.CUDA)
    with profile(activities=activities) as prof:
        result = run()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
    table = prof.key_averages()
    by = "self_cuda_time_total" if device.startswith("cuda") else "self_cpu_time_total"
    return {
        "timings_ms": result.timings_ms,
        "by_self_device_time": table.table(sort_by=by, row_limit=ROWS),
        "by_self_cpu_time": table.table(sort_by="self_cpu_time_total", row_limit=ROWS),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--batch", type=int, default=64, help="images of Pipeline.estimate")
    parser.add_argument("--poses", type=int, default=1024, help="2D poses of Lifter.lift")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    pipeline = Pipeline.load(device=args.device)
    images = bench_images(args.batch)
    poses = benchmark_poses(pipeline.lifter, args.poses)
    report = {
        "device": args.device,
        "pipeline": profiled(lambda: pipeline.estimate(images), args.device),
        "lifter": profiled(lambda: pipeline.lifter.lift(poses), args.device),
    }
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    for part in ("pipeline", "lifter"):
        print(f"== {part}\n{report[part]['by_self_device_time']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
