"""Commands of the 3D stage: `ds3d build-db`, `ds3d lift`, `ds3d eval h36m`, `ds3d bench lift`."""

from __future__ import annotations

import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ds3d.cli import write_report
from ds3d.paths import MODELS_DIR
from ds3d.skeleton import SET_NAMES

DEDUPE_MM = 60.0  # measured: 40 mm doubles the database for no gain (docs/RESULTS.md)


def register(commands, evals, benches) -> None:
    p = commands.add_parser("build-db", help="build a 3D pose database from mocap")
    p.add_argument("--source", choices=("h36m", "cmu"), default="h36m")
    p.add_argument("--subjects", default="S1,S5,S6,S7,S8,S9", help="Human3.6M subjects")
    p.add_argument("--bvh", type=Path, nargs="*", help="BVH files or folders (cmu source)")
    p.add_argument("--dedupe-mm", type=float, default=DEDUPE_MM)
    p.add_argument("--out", type=Path, default=MODELS_DIR / "posedb")
    p.set_defaults(func=build_db)

    p = commands.add_parser("lift", help="lift 2D poses (JSON) to 3D")
    p.add_argument(
        "input",
        type=Path,
        help='JSON: {"joints_2d": [[[x, y] x 14], ...], '
        '"intrinsics": optional, "visible": optional}',
    )
    p.add_argument("--out", type=Path, help="result JSON (default: stdout)")
    _model_options(p)
    p.set_defaults(func=lift)

    p = evals.add_parser("h36m", help="Human3.6M protocol with ground-truth 2D (S11)")
    p.add_argument("--subject", default="S11", help="test subject (S9 for tuning on training data)")
    p.add_argument("--stride", type=int, default=64, help="every n-th frame of each sequence")
    p.add_argument("--limit", type=int, help="evaluate only the first n test poses")
    p.add_argument(
        "--variants",
        default="clean,noise5,noise10,outlier40,all-only,unweighted",
        help="comma-separated input/algorithm variants",
    )
    p.add_argument("--out", type=Path, help="JSON report")
    _model_options(p)
    p.set_defaults(func=eval_h36m)

    p = benches.add_parser("retrieval", help="IVF recall@K against the exact (flat) index")
    p.add_argument("--queries", type=int, default=256)
    p.add_argument("--k", type=int, default=256)
    p.add_argument("--nprobe", default="8,16,32")
    p.add_argument("--out", type=Path, help="JSON report")
    _model_options(p)
    p.set_defaults(func=bench_retrieval)

    p = benches.add_parser("lift", help="poses per second and time per stage")
    p.add_argument("--batch-sizes", default="1,16,64")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, help="JSON report")
    _model_options(p)
    p.set_defaults(func=bench_lift)


def _model_options(p) -> None:
    p.add_argument("--model-dir", type=Path, default=MODELS_DIR)
    p.add_argument("--database", default="posedb", help="database folder inside --model-dir")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--threads", type=int, help="torch CPU threads")


def _load_lifter(args, **overrides):
    from ds3d.lifter import Lifter, LifterConfig

    if args.threads:
        torch.set_num_threads(args.threads)
    config = dataclasses.replace(LifterConfig(), **overrides)
    return Lifter.load(args.model_dir, args.device, config, args.database)


def build_db(args) -> int:
    from ds3d.mocap.database import PoseDatabase

    start = time.perf_counter()
    if args.source == "h36m":
        from ds3d.data.h36m import load_h36m_poses

        subjects = tuple(args.subjects.split(","))
        poses = load_h36m_poses(subjects)
        manifest = {"source": "h36m", "subjects": list(subjects)}
    else:
        from ds3d.data.cmu import load_cmu_poses

        poses = load_cmu_poses(args.bvh or None)
        manifest = {
            "source": "cmu",
            "files": [str(p) for p in args.bvh or ["cmu_bvh/*"]],
            "retargeted_to": "h36m median bone lengths",
        }
    db = PoseDatabase.from_world_poses(poses, args.dedupe_mm, manifest)
    db.save(args.out)
    print(
        f"{len(poses)} poses -> {len(db.poses)} after {args.dedupe_mm:g} mm dedupe, "
        f"{len(db)} entries; {time.perf_counter() - start:.1f} s -> {args.out}"
    )
    return 0


def lift(args) -> int:
    request = json.loads(args.input.read_text())
    lifter = _load_lifter(args)
    result = lifter.lift(request["joints_2d"], request.get("visible"), request.get("intrinsics"))
    write_report(
        {
            "model": lifter.model_id,
            # rounded in float64: a rounded float32 prints as -135.7100067138672
            "joints_3d": result.joints_3d.double().numpy().round(2).tolist(),
            "joint_set": result.joint_set,
            "energy": result.energy.tolist(),
            "timings_ms": result.timings_ms,
        },
        args.out,
    )
    return 0


# Variants of eval h36m: (perturbation of the 2D input, LifterConfig overrides).
EVAL_VARIANTS: dict[str, tuple[dict, dict]] = {
    "clean": ({}, {}),
    "noise5": ({"noise_px": 5.0}, {}),
    "noise10": ({"noise_px": 10.0}, {}),
    "outlier40": ({"outlier_px": 40.0}, {}),
    "all-only": ({}, {"joint_sets": ("all",)}),
    "all-only-outlier40": ({"outlier_px": 40.0}, {"joint_sets": ("all",)}),
    "paper-selection": ({}, {"select_on_all_joints": False}),
    "paper-selection-outlier40": ({"outlier_px": 40.0}, {"select_on_all_joints": False}),
    "unweighted": ({}, {"weighting": False}),
    "projection-fit-20": ({}, {"projection_iterations": 20}),
    "pose-fit-30": ({}, {"pose_iterations": 30}),
    "nprobe16": ({}, {"nprobe": 16}),
}


def eval_h36m(args) -> int:
    from ds3d.evaluation.h36m import evaluate, protocol_cases

    cases = protocol_cases(args.subject, args.stride)
    if args.limit:
        cases = cases.subset(np.arange(min(args.limit, len(cases))))
    lifter = _load_lifter(args)
    base = lifter.config
    report = {
        "model": lifter.model_id,
        "database": args.database,
        "subject": args.subject,
        "stride": args.stride,
        "variants": {},
    }
    for name in args.variants.split(","):
        perturbation, overrides = EVAL_VARIANTS[name]
        lifter.configure(dataclasses.replace(base, **overrides))
        start = time.perf_counter()
        result = evaluate(lifter, cases, **perturbation)
        result["seconds"] = round(time.perf_counter() - start, 1)
        report["variants"][name] = result
        print(
            f"{name:>28}: 3D pose error {result['pose_error']:.1f} mm, PA-MPJPE "
            f"{result['pa_mpjpe']:.1f}, MPJPE {result['mpjpe']:.1f} ({result['frames']} poses, "
            f"{result['seconds']} s)",
            file=sys.stderr,
        )
    write_report(report, args.out)
    return 0


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
    lifter = _load_lifter(args)
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
        for r in range(1, args.repeats + 1):
            t = time.perf_counter()
            result = lifter.lift(inputs[r * batch : (r + 1) * batch])
            elapsed += time.perf_counter() - t
            for stage, ms in result.timings_ms.items():
                stages[stage] = stages.get(stage, 0.0) + ms / args.repeats
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

    lifter = _load_lifter(args)
    rng = np.random.default_rng(1)
    queries = benchmark_poses(lifter, args.queries) + rng.normal(0, 5, (args.queries, 14, 2))
    queries = torch.from_numpy(queries.astype(np.float32))
    exact = PoseRetriever(lifter.database, IndexConfig(kind="flat", storage="f32"), cache=False)
    start = time.perf_counter()
    truth = exact.search(queries, args.k)
    report = {
        "k": args.k,
        "queries": args.queries,
        "flat_ms_per_query": round(1000 * (time.perf_counter() - start) / args.queries, 2),
        "ivf": {},
    }
    del exact
    for nprobe in (int(n) for n in args.nprobe.split(",")):
        start = time.perf_counter()
        found = lifter.retriever.search(queries, args.k, nprobe)
        elapsed = time.perf_counter() - start
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
        print(f"nprobe {nprobe}: {report['ivf'][nprobe]}", file=sys.stderr)
    print(f"flat: {report['flat_ms_per_query']} ms/query (5 sets)", file=sys.stderr)
    write_report(report, args.out)
    return 0
