"""`ds3d build-db`: a 3D pose database from motion capture (Human3.6M or CMU BVH);
`ds3d train-prior`: the lifting prior learnt from a database's poses."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ds3d.cli.parser import add_model_options, add_set_option, field_overrides, set_threads
from ds3d.util.paths import MODELS_DIR

DEDUPE_MM = 60.0  # the bundled database's (docs/tuning.md)


def register(commands, evals, benches) -> None:
    p = commands.add_parser("build-db", help="build a 3D pose database from mocap")
    p.add_argument("--source", choices=("h36m", "cmu"), default="h36m")
    p.add_argument("--subjects", default="S1,S5,S6,S7,S8,S9", help="Human3.6M subjects")
    p.add_argument("--bvh", type=Path, nargs="*", help="BVH files or folders (cmu source)")
    p.add_argument(
        "--native-proportions",
        action="store_true",
        help="cmu source: keep the BVH skeletons' own bone lengths (default: Human3.6M's medians)",
    )
    p.add_argument("--dedupe-mm", type=float, default=DEDUPE_MM)
    p.add_argument("--out", type=Path, default=MODELS_DIR / "posedb")
    p.set_defaults(func=build_db)

    p = commands.add_parser(
        "train-prior", help="train the lifting prior of a pose database, from its poses alone"
    )
    add_model_options(p, threads=None)
    p.add_argument(
        "--out", type=Path, help="the prior's folder (default: MODEL_DIR/DATABASE/prior)"
    )
    add_set_option(p, "override a PriorTraining field (ds3d.training.prior), e.g. steps=20000")
    p.set_defaults(func=train_prior)


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

        poses = load_cmu_poses(args.bvh or None, retarget=not args.native_proportions)
        manifest = {"source": "cmu", "files": [str(p) for p in args.bvh or ["cmu_bvh/*"]]}
        if not args.native_proportions:
            manifest["retargeted_to"] = "h36m median bone lengths"
    db = PoseDatabase.from_world_poses(poses, args.dedupe_mm, manifest)
    db.save(args.out)
    print(
        f"{len(poses)} poses -> {len(db.poses)} after {args.dedupe_mm:g} mm dedupe, "
        f"{len(db)} entries; {time.perf_counter() - start:.1f} s -> {args.out}"
    )
    return 0


def train_prior(args) -> int:
    from ds3d.mocap.database import PoseDatabase
    from ds3d.mocap.prior import PRIOR_DIR
    from ds3d.training.prior import PriorTraining
    from ds3d.training.prior import train_prior as train
    from ds3d.util.progress import logging_above_bars

    set_threads(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cfg = PriorTraining(**field_overrides(PriorTraining, args.set))
    db = PoseDatabase.load(args.model_dir / args.database)
    out = args.out or args.model_dir / args.database / PRIOR_DIR
    with logging_above_bars():
        prior = train(db, cfg)
    prior.save(out)
    for name, metrics in prior.manifest["metrics"].items():
        print(f"{name}: loss {metrics['train_loss']:.4g}, validation {metrics['validation']:.4g}")
    print(f"{prior.manifest['seconds']:.0f} s -> {out}")
    return 0
