"""`ds3d train-2d`, `ds3d eval lsp`, `ds3d bench 2d`: the 2D stage's command line."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from ds3d.cli import field_overrides, write_report
from ds3d.data.lsp import PoseAnnotations, load_lsp
from ds3d.evaluation.metrics import pck, pixel_error
from ds3d.image2d.estimator import Estimate2D, EstimatorParams, PoseEstimator2D, read_manifest
from ds3d.image2d.train import (
    NET_FILES,
    TrainConfig,
    fit_jointnet,
    train,
    training_annotations,
    write_manifest,
)
from ds3d.image_io import read_image
from ds3d.paths import MODELS_DIR, data_root, project_relative
from ds3d.skeleton import JOINT_NAMES

DEFAULT_MODEL = MODELS_DIR / "image2d"

# `--small`: a few dozen images and a handful of shallow trees; trains in well under a minute
# and exists to exercise the whole path (tests, CI), not to be accurate.
SMALL = {
    "max_images": 40,
    "trees": (3, 3),
    "images_per_tree": 20,
    "pool_size": 128,
    "max_depth": 10,
    "min_samples_leaf": 5,
    "psm_iterations": 10,
    "facing_epochs": 1,
    "jointnet_epochs": 1,
}


INFERENCE_OVERRIDE = "override an EstimatorParams field of the model at inference (e.g. n_scales=4)"


def register(commands, evals, benches) -> None:
    p = commands.add_parser("train-2d", help="train the 2D pose model (forest cascade + PSM)")
    p.add_argument("--out", type=Path, default=DEFAULT_MODEL)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--n-val",
        type=int,
        default=TrainConfig.n_val,
        help="last LSP train images held out for validation",
    )
    p.add_argument("--small", action="store_true", help="tiny model in under a minute (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-eval", action="store_true", help="skip the validation metrics")
    p.add_argument(
        "--observer-labels",
        action="store_true",
        help="observer-centric cascade + facing model (measured no better; see docs/RESULTS.md)",
    )
    _set_option(p, "an EstimatorParams field to train with (e.g. context_pose_sigma=none)")
    p.set_defaults(func=cmd_train)

    j = commands.add_parser(
        "train-jointnet", help="(re)train only the joint network of a 2D model, in place"
    )
    j.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    j.add_argument("--threads", type=int, default=2)
    j.add_argument("--no-eval", action="store_true", help="skip the validation metrics")
    j.set_defaults(func=cmd_train_jointnet)

    e = evals.add_parser("lsp", help="PCK@0.2 on LSP test (im1001-im2000)")
    e.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    e.add_argument(
        "--split",
        choices=("test", "train"),
        default="test",
        help="train: for tuning on the images a model holds out (see --start)",
    )
    e.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    e.add_argument("--limit", type=int, default=None, help="first N images only (after --start)")
    e.add_argument("--batch", type=int, default=16)
    e.add_argument("--threads", type=int, default=1)
    e.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    e.add_argument(
        "--write-manifest", action="store_true", help="record the metrics in the model manifest"
    )
    _set_option(e, INFERENCE_OVERRIDE)
    e.set_defaults(func=cmd_eval_lsp)

    b = benches.add_parser("2d", help="images/s of the 2D stage, time per step")
    b.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    b.add_argument("--threads", type=int, default=1)
    b.add_argument("--repeats", type=int, default=3)
    _set_option(b, INFERENCE_OVERRIDE)
    b.set_defaults(func=cmd_bench)


def _set_option(parser, text: str) -> None:
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=text)


def load_estimator(args) -> PoseEstimator2D:
    """The model of --model with the --set overrides of its inference parameters."""
    est = PoseEstimator2D.load(args.model)
    est.params = dataclasses.replace(est.params, **field_overrides(EstimatorParams, args.set))
    return est


def cmd_train(args) -> int:
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cfg = TrainConfig(seed=args.seed, n_val=args.n_val, **(SMALL if args.small else {}))
    overrides = field_overrides(EstimatorParams, args.set)
    params = EstimatorParams(**{"observer_labels": args.observer_labels, **overrides})
    evaluate = None if args.no_eval else (lambda d: evaluate_validation(d, cfg))
    manifest = train(cfg, params, args.out, evaluate=evaluate)
    print(json.dumps({k: manifest[k] for k in ("train_seconds", "metrics")}, indent=2))
    return 0


def cmd_train_jointnet(args) -> int:
    """Train the joint network on the training images of the model's own manifest (its seed,
    held-out count and image cap) and add it to the model: what `train-2d` does beside the
    forests, on --threads threads instead of one."""
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    manifest = read_manifest(args.model)
    saved = manifest["train_config"]
    cfg = TrainConfig(**{**saved, "trees": tuple(saved["trees"])})
    params = EstimatorParams(**manifest["params"])
    t0 = time.perf_counter()
    state = fit_jointnet(training_annotations(cfg)[0], params, cfg)
    torch.save(state, args.model / NET_FILES["jointnet"])
    manifest["jointnet"] = NET_FILES["jointnet"]
    manifest["train_config"] = dataclasses.asdict(cfg)
    manifest["train_seconds"]["jointnet"] = round(time.perf_counter() - t0, 1)
    write_manifest(args.model, manifest)
    if not args.no_eval:
        manifest.setdefault("metrics", {})["validation"] = evaluate_validation(args.model, cfg)
        write_manifest(args.model, manifest)
    print(json.dumps({k: manifest[k] for k in ("train_seconds", "metrics")}, indent=2))
    return 0


def evaluate_validation(model_dir: Path, cfg: TrainConfig) -> dict:
    _, val = training_annotations(cfg)
    return evaluate(PoseEstimator2D.load(model_dir), val)


def argmax_joints(res: Estimate2D) -> torch.Tensor:
    """No PSM: per joint, the best cell of the returned unaries (the forests', plus the joint
    network's where the model has one). (B, 14, 2) px."""
    b, j, _, w = res.unaries.shape
    best = res.unaries.reshape(b, j, -1).argmax(-1)
    uv1 = torch.stack([best % w, best // w, torch.ones_like(best)], -1).float()
    return torch.einsum("bij,bkj->bki", res.map_to_image, uv1)


def evaluate(est: PoseEstimator2D, ann: PoseAnnotations, batch: int = 16) -> dict:
    """PCK@0.2 (torso = mean of the two shoulder-hip diagonals) per joint and mean, and mean
    pixel error, over all 14 joints of every image (LSP's protocol, occluded joints included),
    for the full model (pyramid + PSM) and for the unaries alone (argmax_joints: the argmax of
    each joint's unary map at the scale the PSM chose, with its left/right decision)."""
    preds, argmax = [], []
    t0 = time.perf_counter()
    for i in range(0, len(ann), batch):
        images = [read_image(p) for p in ann.image_paths[i : i + batch]]
        res = est.estimate(images)
        preds.append(res.joints_2d)
        argmax.append(argmax_joints(res))
    seconds = time.perf_counter() - t0
    gt = torch.from_numpy(ann.joints)
    out = {"n_images": len(ann), "seconds": round(seconds, 1)}
    for name, pred in (("psm", torch.cat(preds)), ("unary_argmax", torch.cat(argmax))):
        per_joint = pck(pred, gt)
        out[name] = {
            "pck@0.2": round(float(per_joint.mean()), 4),
            "pck@0.2_per_joint": {
                n: round(float(v), 4) for n, v in zip(JOINT_NAMES, per_joint, strict=True)
            },
            "mean_pixel_error": round(float(pixel_error(pred, gt).mean()), 2),
        }
    return out


def cmd_eval_lsp(args) -> int:
    if args.write_manifest and (args.split != "test" or args.start or args.set):
        raise SystemExit("--write-manifest records LSP test results of the model as saved")
    torch.set_num_threads(args.threads)
    est = load_estimator(args)
    ann = load_lsp(split=args.split)
    end = len(ann) if args.limit is None else min(args.start + args.limit, len(ann))
    ann = ann.subset(range(args.start, end))
    first = 1 if args.split == "train" else 1001
    result = {
        "dataset": f"LSP {args.split} im{first + args.start:04d}-im{first + end - 1:04d}",
        "model": project_relative(args.model),
        "overrides": args.set,
    }
    result |= evaluate(est, ann, batch=args.batch)
    write_report(result, args.out)
    if args.write_manifest:
        manifest = read_manifest(args.model)
        key = "lsp_test" if args.limit is None else f"lsp_test_first_{args.limit}"
        manifest.setdefault("metrics", {})[key] = result
        write_manifest(args.model, manifest)
    return 0


def _bench_images(size: tuple[int, int] | None, n: int) -> list[np.ndarray]:
    """n LSP test images (resized to size = (w, h) if given); random noise without the data."""
    if (data_root() / "lsp" / "joints.mat").is_file():
        images = [read_image(p) for p in load_lsp(split="test").image_paths[:n]]
    else:  # no dataset here: noise of LSP's typical size
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (175, 110, 3), dtype=np.uint8) for _ in range(n)]
    if size is not None:
        images = [cv2.resize(im, size, interpolation=cv2.INTER_LINEAR) for im in images]
    return images


def cmd_bench(args) -> int:
    torch.set_num_threads(args.threads)
    est = load_estimator(args)
    rows = []
    for label, size in (("lsp-sized", None), ("640x480", (640, 480))):
        images = _bench_images(size, 16)
        for batch in (1, 16):
            est.estimate(images[:batch])  # warm-up
            steps = {"features": 0.0, "traversal": 0.0, "jointnet": 0.0, "psm": 0.0, "total": 0.0}
            for _ in range(args.repeats):
                res = est.estimate(images[:batch])
                for k in steps:
                    steps[k] += res.timings[k]
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
                "select_stride": est.params.select_stride,
                "coarse_trees": est.params.coarse_trees,
                "step_ms": "summed over the threads (CPU time); total is wall-clock",
            }
        ),
        file=sys.stderr,
    )
    return 0
