"""The pipeline's commands: `ds3d predict`, `ds3d gallery`, `ds3d eval lsp-pipeline`,
`ds3d bench pipeline`."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ds3d.cli import field_overrides, write_report
from ds3d.paths import MODELS_DIR

# The refinement table's variants (the paper's fig:query protocol: one iteration, K = 256
# without weighting), and the full method (K = 256 -> K_w = 64 weighted, two iterations).
VARIANTS = {
    "full": ({}, {}),
    "all-only": ({"iterations": 1}, {"joint_sets": ("all",), "weighting": False}),
    "energy": ({"iterations": 1, "selection": "energy"}, {"weighting": False}),
    "posterior": ({"iterations": 1}, {"weighting": False}),
}


def register(commands, evals, benches) -> None:
    p = commands.add_parser("predict", help="2D and 3D pose of the person in each image")
    p.add_argument("images", type=Path, nargs="+")
    p.add_argument(
        "--bbox",
        action="append",
        help="person box x,y,w,h in px; give it once per image, in order (default: whole image)",
    )
    p.add_argument("--iterations", type=int, default=None, help="default: 2 (the paper's)")
    p.add_argument("--out", type=Path, required=True, help="result JSON")
    p.add_argument("--render", type=Path, help="PNG; with several images, PATH-<i>.png for image i")
    _model_options(p)
    p.set_defaults(func=predict)

    p = commands.add_parser("gallery", help="renders of LSP test images picked by a seed")
    p.add_argument("--n", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("docs/gallery"))
    _model_options(p)
    p.set_defaults(func=gallery)

    p = evals.add_parser(
        "lsp-pipeline", help="2D accuracy of the refinement (iterations, joint-set ablation) on LSP"
    )
    p.add_argument("--split", choices=("test", "train"), default="test")
    p.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    p.add_argument("--every", type=int, default=1, help="every n-th image of the split")
    p.add_argument("--limit", type=int, help="at most this many images (after --every)")
    p.add_argument("--variants", default=",".join(VARIANTS), help=f"of {', '.join(VARIANTS)}")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a PipelineConfig field in every variant (e.g. min_var=4)",
    )
    p.add_argument("--out", type=Path, help="JSON report")
    _model_options(p)
    p.set_defaults(func=eval_lsp)

    p = benches.add_parser("pipeline", help="images/s end to end and the time of each stage")
    p.add_argument("--batch-sizes", default="1,16")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=Path, help="JSON report")
    _model_options(p)
    p.set_defaults(func=bench)


def _model_options(p) -> None:
    p.add_argument("--model-dir", type=Path, default=MODELS_DIR, help="holds image2d/, posedb/")
    p.add_argument("--database", default="posedb", help="pose database folder in --model-dir")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")


def _load(args):
    from ds3d.pipeline import Pipeline

    torch.set_num_threads(args.threads)
    return Pipeline.load(args.model_dir, database=args.database)


def corner_box(text: str) -> tuple[float, float, float, float]:
    """'x,y,w,h' px -> (x0, y0, x1, y1), the 2D stage's box."""
    values = [float(v) for v in text.split(",")]
    if len(values) != 4 or not np.isfinite(values).all() or values[2] <= 0 or values[3] <= 0:
        raise SystemExit(f"--bbox wants x,y,w,h with w, h > 0; got {text!r}")
    x, y, w, h = values
    return (x, y, x + w, y + h)


def predict(args) -> int:
    from ds3d.image_io import read_image
    from ds3d.skeleton import JOINT_NAMES

    if args.bbox is not None and len(args.bbox) != len(args.images):
        raise SystemExit(f"{len(args.bbox)} --bbox for {len(args.images)} images: one per image")
    pipeline = _load(args)
    images = [read_image(path) for path in args.images]
    boxes = None if args.bbox is None else [corner_box(b) for b in args.bbox]
    result = pipeline.estimate(images, bboxes=boxes, iterations=args.iterations)
    report = {
        "model": pipeline.model_id,
        "joint_names": list(JOINT_NAMES),
        "units": {"joints_2d": "px", "joints_3d": "mm, camera-oriented, root at the hips"},
        "timings_ms": result.timings_ms,
        "items": [{"image": str(path), **result.item(i)} for i, path in enumerate(args.images)],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    if args.render is not None:
        from ds3d.render import render

        for i, image in enumerate(images):
            path = args.render
            if len(images) > 1:
                path = path.with_name(f"{path.stem}-{i}{path.suffix or '.png'}")
            render(
                path,
                image,
                result.joints_2d[i].numpy(),
                result.joints_3d[i].numpy(),
                result.joints_2d_initial[i].numpy(),
                caption=f"{args.images[i].name}: joint set {result.joint_set[i]}",
            )
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def gallery(args) -> int:
    """Random picks, not the best ones: the gallery shows successes and failures alike."""
    from ds3d.data.lsp import load_lsp
    from ds3d.evaluation.metrics import pck
    from ds3d.image_io import read_image
    from ds3d.render import render

    pipeline = _load(args)
    ann = load_lsp(split="test")
    picks = sorted(np.random.default_rng(args.seed).choice(len(ann), args.n, replace=False))
    images = [read_image(ann.image_paths[i]) for i in picks]
    result = pipeline.estimate(images)
    args.out.mkdir(parents=True, exist_ok=True)
    gt = torch.from_numpy(ann.joints[picks])
    for j, i in enumerate(picks):
        name = ann.image_paths[i].stem
        correct = float(pck(result.joints_2d[j : j + 1], gt[j : j + 1]).mean())
        caption = (
            f"LSP {name}: joint set {result.joint_set[j]}, "
            f"{round(14 * correct)}/14 joints within PCK@0.2"
        )
        render(
            args.out / f"{name}.png",
            images[j],
            result.joints_2d[j].numpy(),
            result.joints_3d[j].numpy(),
            result.joints_2d_initial[j].numpy(),
            caption=caption,
        )
        print(args.out / f"{name}.png", caption)
    return 0


def _metrics(pred: torch.Tensor, gt: torch.Tensor) -> dict:
    from ds3d.evaluation.metrics import pck, pixel_error

    return {
        "pck@0.2": round(float(pck(pred, gt).mean()), 4),
        "mean_pixel_error": round(float(pixel_error(pred, gt).mean()), 2),
    }


def eval_lsp(args) -> int:
    """LSP's protocol as the 2D stage's `ds3d eval lsp`: all 14 joints of every image."""
    from ds3d.data.lsp import load_lsp
    from ds3d.image_io import read_image

    names = [v for v in args.variants.split(",") if v]
    unknown = set(names) - set(VARIANTS)
    if unknown:
        raise SystemExit(f"unknown variants {sorted(unknown)}; known: {', '.join(VARIANTS)}")
    pipeline = _load(args)
    ann = load_lsp(split=args.split)
    ann = ann.subset(range(args.start, len(ann), args.every))
    if args.limit is not None:
        ann = ann.subset(range(min(args.limit, len(ann))))
    preds: dict[str, list[torch.Tensor]] = {"initial": []}
    seconds = dict.fromkeys(["2d", *names], 0.0)
    for start in range(0, len(ann), args.batch):
        t0 = time.perf_counter()
        images = [read_image(p) for p in ann.image_paths[start : start + args.batch]]
        estimate = pipeline.estimator.estimate(images)
        seconds["2d"] += time.perf_counter() - t0
        preds["initial"].append(estimate.joints_2d)
        for name in names:
            t0 = time.perf_counter()
            pipeline.config, lifter_config = _configs(name, args.set)
            pipeline.lifter.configure(lifter_config)
            res = pipeline.lift_estimate(estimate)
            for t in range(res.iterations):
                preds.setdefault(f"{name}/iteration{t + 1}", []).append(
                    res.joints_2d_iterations[:, t]
                )
            seconds[name] += time.perf_counter() - t0
        print(f"{start + len(images)}/{len(ann)} images", file=sys.stderr, flush=True)
    gt = torch.from_numpy(ann.joints)
    split = "test im1001-im2000" if args.split == "test" else "train im0001-im1000"
    report = {
        "dataset": f"LSP {split}, images [{args.start}::{args.every}] of the split",
        "n_images": len(ann),
        "threads": args.threads,
        "variants": {n: _describe(*_configs(n, args.set)) for n in names},
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "results": {k: _metrics(torch.cat(v), gt) for k, v in preds.items()},
    }
    write_report(report, args.out)
    return 0


def _configs(name: str, overrides: list[str] = ()):
    """The configurations of a variant, with NAME=VALUE overrides of PipelineConfig fields."""
    from ds3d.lifter import LifterConfig
    from ds3d.pipeline import PipelineConfig

    config, lifter_config = VARIANTS[name]
    extra = field_overrides(PipelineConfig, overrides)
    return PipelineConfig(**(config | extra)), LifterConfig(**lifter_config)


def _describe(config, lifter_config) -> dict:
    keep = ("neighbours", "weighted_neighbours", "weighting", "joint_sets")
    return dataclasses.asdict(config) | {k: getattr(lifter_config, k) for k in keep}


def _bench_images(n: int) -> list[np.ndarray]:
    """n LSP test images, or noise of LSP's typical size where the dataset is absent."""
    from ds3d.data.lsp import load_lsp
    from ds3d.image_io import read_image
    from ds3d.paths import data_root

    if (data_root() / "lsp" / "joints.mat").is_file():
        return [read_image(p) for p in load_lsp(split="test").image_paths[:n]]
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (175, 110, 3), dtype=np.uint8) for _ in range(n)]


def bench(args) -> int:
    pipeline = _load(args)
    sizes = [int(b) for b in args.batch_sizes.split(",")]
    images = _bench_images(max(sizes))
    rows = []
    for batch in sizes:
        pipeline.estimate(images[:batch])  # warm-up
        stages: dict[str, float] = {}
        for _ in range(args.repeats):
            res = pipeline.estimate(images[:batch])
            for stage, ms in res.timings_ms.items():
                stages[stage] = stages.get(stage, 0.0) + ms
        n = args.repeats * batch
        rows.append(
            {
                "batch": batch,
                "images_per_s": round(1000 * n / stages["total"], 2),
                "ms_per_image": {k: round(v / n, 1) for k, v in stages.items()},
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    report = {"threads": args.threads, "iterations": pipeline.config.iterations, "rows": rows}
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2) + "\n")
    return 0
