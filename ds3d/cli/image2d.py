"""The 2D stage's commands: `ds3d train-2d`, `ds3d train-jointnet`, `ds3d eval lsp`."""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import asdict, fields, replace
from pathlib import Path
from typing import Any

import torch

from ds3d.cli.parser import (
    DEFAULT_IMAGE2D,
    add_device_option,
    add_set_option,
    field_overrides,
    write_report,
)
from ds3d.data.lsp import load_lsp, load_lspet
from ds3d.evaluation.lsp import evaluate_2d
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.model_files import NET_FILES, record_metrics, replace_jointnet, training_setup
from ds3d.image2d.params import EstimatorParams, InferenceParams
from ds3d.training.config import TrainConfig
from ds3d.training.image2d import CHECKPOINT_DIR, train
from ds3d.training.images import training_annotations
from ds3d.training.jointnet import fit_jointnet
from ds3d.util.paths import project_relative
from ds3d.util.progress import logging_above_bars

# `--small`: a few dozen images and a handful of shallow trees; trains in well under a minute
# and exists to exercise the whole path (tests, CI), not to be accurate.
SMALL: dict[str, Any] = {  # TrainConfig's fields for --small
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

INFERENCE_OVERRIDE = "override an InferenceParams field of the model (e.g. n_scales=4)"
RESUME = f"continue from the progress saved in the model folder's {CHECKPOINT_DIR}/"


def register(commands, evals, benches) -> None:
    p = commands.add_parser("train-2d", help="train the 2D pose model (forest cascade + PSM)")
    p.add_argument("--out", type=Path, default=DEFAULT_IMAGE2D)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--n-val",
        type=int,
        default=TrainConfig.n_val,
        help="last LSP train images held out for validation",
    )
    p.add_argument(
        "--lspet-val",
        type=int,
        default=TrainConfig.lspet_val,
        help="last LSPet images held out for validation (a second set, of other looks)",
    )
    p.add_argument("--small", action="store_true", help="tiny model in under a minute (tests)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-eval", action="store_true", help="skip the validation metrics")
    p.add_argument("--resume", action="store_true", help=RESUME)
    p.add_argument(
        "--no-jointnet",
        action="store_true",
        help="no joint network: `ds3d train-jointnet --model OUT` adds it, on more threads",
    )
    p.add_argument(
        "--observer-labels",
        action="store_true",
        help="observer-centric cascade + facing model (measured no better; see docs/tuning.md)",
    )
    add_set_option(p, "an EstimatorParams field to train with (e.g. context_pose_sigma=none)")
    p.set_defaults(func=cmd_train)

    j = commands.add_parser(
        "train-jointnet", help="(re)train only the joint network of a 2D model, in place"
    )
    j.add_argument("--model", type=Path, default=DEFAULT_IMAGE2D)
    j.add_argument("--threads", type=int, default=2)
    j.add_argument("--no-eval", action="store_true", help="skip the validation metrics")
    j.add_argument("--resume", action="store_true", help=RESUME)
    j.add_argument(
        "--from-current",
        action="store_true",
        help="go on training the model's joint network rather than start from scratch",
    )
    add_set_option(j, "a TrainConfig jointnet_* field to train with (e.g. jointnet_epochs=40)")
    j.set_defaults(func=cmd_train_jointnet)

    q = commands.add_parser(
        "quantize-jointnet",
        help="the int8 copy of a 2D model's joint network that the people search runs on a CPU",
        description="Calibrated on the search's levels of LSP train's first images (never held "
        "out) and written into the model (jointnet_int8.onnx; ds3d.image2d.quantized).",
    )
    q.add_argument("--model", type=Path, default=DEFAULT_IMAGE2D)
    q.add_argument("--images", type=int, default=100, help="LSP train images to calibrate on")
    q.add_argument("--threads", type=int, default=2)
    q.set_defaults(func=cmd_quantize_jointnet)

    e = evals.add_parser("lsp", help="PCK@0.2 on LSP test (im1001-im2000)")
    e.add_argument("--model", type=Path, default=DEFAULT_IMAGE2D)
    e.add_argument(
        "--split",
        choices=("test", "train", "lspet"),
        default="test",
        help="train: for tuning on the images a model holds out (see --start); lspet: LSPet, "
        "whose last images a model trained with --lspet-val holds out",
    )
    e.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    e.add_argument("--limit", type=int, default=None, help="first N images only (after --start)")
    e.add_argument("--batch", type=int, default=16)
    e.add_argument("--threads", type=int, default=1)
    add_device_option(e, "where the 2D stage runs")
    e.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    e.add_argument(
        "--write-manifest", action="store_true", help="record the metrics in the model manifest"
    )
    add_set_option(e, INFERENCE_OVERRIDE)
    e.set_defaults(func=cmd_eval_lsp)


def load_estimator(args) -> PoseEstimator2D:
    """The 2D model of --model (on --device, where the command has one) with
    the --set overrides of its inference parameters."""
    est = PoseEstimator2D.load(args.model, getattr(args, "device", "cpu"))
    est.params = est.params.with_inference(**field_overrides(InferenceParams, args.set))
    return est


def cmd_train(args) -> int:
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    cfg = TrainConfig(
        seed=args.seed, n_val=args.n_val, lspet_val=args.lspet_val, **(SMALL if args.small else {})
    )
    if args.no_jointnet:
        cfg = replace(cfg, jointnet_epochs=0)
    overrides = field_overrides(EstimatorParams, args.set)
    params = EstimatorParams(**{"observer_labels": args.observer_labels, **overrides})
    evaluate = None if args.no_eval else (lambda d: evaluate_validation(d, cfg))
    with logging_above_bars():
        manifest = train(cfg, params, args.out, evaluate=evaluate, resume=args.resume)
    print(json.dumps({k: manifest[k] for k in ("train_seconds", "metrics")}, indent=2))
    return 0


def cmd_train_jointnet(args) -> int:
    """Train the joint network on the training images of the model's own manifest (its seed,
    held-out count and image cap) with the network's TrainConfig defaults (and --set), and put
    it in the model: what `train-2d` does beside the forests, on --threads threads instead of
    one. Progress is saved after every epoch; --resume continues from it."""
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    saved, params = training_setup(args.model)
    overrides = field_overrides(TrainConfig, args.set)
    if any(not name.startswith("jointnet_") for name in overrides):
        raise SystemExit("train-jointnet --set takes the jointnet_* fields of TrainConfig")
    defaults = {f.name: f.default for f in fields(TrainConfig) if f.name.startswith("jointnet_")}
    cfg = replace(TrainConfig.from_saved(saved), **(defaults | overrides))
    checkpoint = args.model / CHECKPOINT_DIR / "jointnet.pt"
    if not args.resume:
        checkpoint.unlink(missing_ok=True)
    with logging_above_bars():
        init = None
        if args.from_current:
            init = torch.load(args.model / NET_FILES["jointnet"], weights_only=True)
        annotations = training_annotations(cfg)[0]
        state, seconds = fit_jointnet(annotations, params, cfg, checkpoint, init)
    manifest = replace_jointnet(args.model, state, cfg.jointnet_shape(), asdict(cfg), seconds)
    shutil.rmtree(args.model / CHECKPOINT_DIR)
    if not args.no_eval:
        manifest = record_metrics(args.model, "validation", evaluate_validation(args.model, cfg))
    print(json.dumps({k: manifest[k] for k in ("train_seconds", "metrics")}, indent=2))
    return 0


def evaluate_validation(model_dir: Path, cfg: TrainConfig) -> dict:
    """LSP's protocol on the images the training of `cfg` held out: LSP train's last n_val,
    and LSPet's last lspet_val under "lspet" (PCK over the joints LSPet places)."""
    _, val, lspet_val = training_annotations(cfg)
    estimator = PoseEstimator2D.load(model_dir)
    result = evaluate_2d(estimator, val)
    if len(lspet_val):
        result["lspet"] = evaluate_2d(estimator, lspet_val)
    return result


def cmd_eval_lsp(args) -> int:
    if args.write_manifest and (args.split != "test" or args.start or args.set):
        raise SystemExit("--write-manifest records LSP test results of the model as saved")
    torch.set_num_threads(args.threads)
    est = load_estimator(args)
    ann = load_lspet() if args.split == "lspet" else load_lsp(split=args.split)
    end = len(ann) if args.limit is None else min(args.start + args.limit, len(ann))
    ann = ann.subset(range(args.start, end))
    first = 1001 if args.split == "test" else 1
    digits = 5 if args.split == "lspet" else 4
    name = "LSPet" if args.split == "lspet" else f"LSP {args.split}"
    result = {
        "dataset": f"{name} im{first + args.start:0{digits}d}-im{first + end - 1:0{digits}d}",
        "model": project_relative(args.model),
        "overrides": args.set,
    }
    result |= evaluate_2d(est, ann, batch=args.batch)
    write_report(result, args.out)
    if args.write_manifest:
        key = "lsp_test" if args.limit is None else f"lsp_test_first_{args.limit}"
        record_metrics(args.model, key, result)
    return 0


def cmd_quantize_jointnet(args) -> int:
    from ds3d.training.quantize import quantize_model

    torch.set_num_threads(args.threads)
    manifest = quantize_model(args.model, args.images)
    print(json.dumps(manifest["jointnet_int8_calibration"]))
    return 0
