"""The pipeline's commands: `ds3d predict`, `ds3d gallery`, `ds3d eval lsp-pipeline`, `ds3d eval
people`."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import torch

from ds3d.cli.parser import (
    add_model_options,
    add_people_options,
    add_set_option,
    field_overrides,
    write_report,
)
from ds3d.evaluation.lsp import REFINEMENT_VARIANTS, evaluate_refinement
from ds3d.fit.camera import ASSUMED_FOV_DEG


def register(commands, evals, benches) -> None:
    p = commands.add_parser(
        "predict",
        help="2D and 3D poses of the people in images, folders, videos, a webcam or URLs",
        description="Writes OUT/predictions.jsonl (a line per image or frame) and, for each "
        "video, OUT/NAME_3d.npz and .csv; the options add more (ds3d.io.writers).",
    )
    p.add_argument(
        "sources",
        nargs="+",
        help="image files, folders (every image below, found by content), globs, video files, "
        "a webcam index (0) or http(s) URLs",
    )
    p.add_argument("--out", type=Path, default=Path("predictions"), help="output folder")
    p.add_argument("--batch-size", type=int, default=16, help="images estimated at once")
    p.add_argument("--stride", type=int, default=1, help="every n-th frame of a video or webcam")
    add_people_options(p)
    p.add_argument(
        "--bbox",
        help="the person's box x,y,w,h in px, the same in every image (default: people are "
        "searched for; the Python API and the service take corners x0, y0, x1, y1)",
    )
    p.add_argument("--iterations", type=int, default=None, help="default: 1 (the paper's: 2)")
    p.add_argument(
        "--focal-px",
        type=float,
        help="the camera's focal length in px, which places the people in its coordinates "
        f"(root_position; default: a {ASSUMED_FOV_DEG:g}-degree field of view is assumed)",
    )
    p.add_argument(
        "--no-smooth",
        action="store_true",
        help="leave the 3D joints of videos and webcams as estimated frame by frame (by default "
        "each tracked person's are smoothed: ds3d.tracking)",
    )
    p.add_argument("--json", action="store_true", help="also OUT/json/: a JSON file per image")
    p.add_argument("--coco", action="store_true", help="also OUT/coco_keypoints.json")
    p.add_argument(
        "--bvh",
        action="store_true",
        help="also the joint angles as BVH: OUT/bvh/*.bvh per image and person (one frame), "
        "OUT/NAME_K.bvh per video and tracked person K",
    )
    p.add_argument(
        "--overlay",
        action="store_true",
        help="also the skeletons drawn: OUT/overlay/*.jpg per image, OUT/NAME_overlay.mp4 per "
        "video (2D over the frame, 3D beside it)",
    )
    p.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        default="cpu",
        help="where both stages run",
    )
    add_model_options(p, threads=min(2, os.cpu_count() or 1))
    add_workers_option(p)
    p.set_defaults(func=predict)

    p = commands.add_parser("gallery", help="renders of LSP test images picked by a seed")
    p.add_argument("--n", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("docs/gallery"))
    p.add_argument(
        "--photos",
        type=Path,
        help="instead, every photo of this folder, every person found, into OUT/photos",
    )
    add_model_options(p)
    p.set_defaults(func=gallery)

    variants = ",".join(REFINEMENT_VARIANTS)
    p = evals.add_parser(
        "lsp-pipeline", help="2D accuracy of the refinement (iterations, joint-set ablation) on LSP"
    )
    p.add_argument("--split", choices=("test", "train"), default="test")
    p.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    p.add_argument("--every", type=int, default=1, help="every n-th image of the split")
    p.add_argument("--limit", type=int, help="at most this many images (after --every)")
    p.add_argument("--variants", default=variants, help=f"of {variants}")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a PipelineConfig field in every variant (e.g. refine.min_var=4)",
    )
    p.add_argument(
        "--searched",
        action="store_true",
        help="also each image without its box: the best person the search finds",
    )
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p)
    p.set_defaults(func=eval_lsp_pipeline)

    p = evals.add_parser(
        "joint-confidence",
        help="how often joints are right at each confidence (LSP, searched); --fit calibrates",
        description="Each image searched, its best person: the expected calibration error and "
        "reliability of the per-joint confidences, a joint being right within PCK@0.2 "
        "(ds3d.confidence). --fit fits the calibration on these images and writes it beside "
        "the 2D model (MODEL_DIR/image2d/joint_calibration.json); fit on held-out images "
        "(--split train --start 700) only.",
    )
    p.add_argument("--split", choices=("test", "train"), default="test")
    p.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    p.add_argument("--limit", type=int, help="at most this many images")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--fit", action="store_true", help="fit and write the calibration")
    p.add_argument("--plot", type=Path, help="also the reliability diagram as a PNG")
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, threads=min(2, os.cpu_count() or 1))
    p.set_defaults(func=eval_joint_confidence)

    p = evals.add_parser(
        "people", help="people of any size in 640x480 canvases built from LSP: detection and PCK"
    )
    p.add_argument(
        "--split",
        choices=("test", "train", "lspet"),
        default="test",
        help="LSP's people, or LSPet's with every joint annotated",
    )
    p.add_argument(
        "--start",
        type=int,
        default=0,
        help="skip the split's first n images (held out: train 700, lspet 9000)",
    )
    p.add_argument("--count", type=int, default=200, help="canvases")
    p.add_argument("--seed", type=int, default=0, help="draws the canvases")
    p.add_argument(
        "--empty",
        type=float,
        default=0.0,
        help="the share of canvases without people, filled from beside an LSP image's person",
    )
    p.add_argument(
        "--cut", type=float, default=0.0, help="each person's chance to be cut by the canvas's edge"
    )
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--save", type=Path, help="also write the canvases as PNG into this folder")
    p.add_argument(
        "--calibrate-also",
        action="append",
        default=[],
        metavar="SPLIT:START",
        help="also fit the person score on this split's canvases (drawn alike), with this run's: "
        "calibration_pooled in the report (e.g. lspet:9000; repeatable)",
    )
    p.add_argument("--plot", type=Path, help="also the person score's reliability diagram, a PNG")
    p.add_argument("--out", type=Path, help="JSON report")
    add_set_option(p, "override a PipelineConfig field (e.g. search.proposal_floor=110)")
    add_model_options(p)
    p.set_defaults(func=eval_people)


def add_workers_option(parser) -> None:
    """--workers: processes that split each batch (ds3d.workers)."""
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes, each its own models with --threads torch threads, that split each "
        "batch (more images/s than as many threads on a CPU; about 1 GB each)",
    )


def load_pipeline(args):
    """The Pipeline of --model-dir and --database, on --device where the command has it (else
    the CPU), on --threads torch threads; with --workers N > 1, a PipelineWorkers of N such
    pipelines (ds3d.workers), whose estimate() is the Pipeline's."""
    from ds3d.pipeline import Pipeline
    from ds3d.workers import PipelineWorkers

    device = getattr(args, "device", "cpu")
    load = {"model_dir": args.model_dir, "device": device, "database": args.database}
    if getattr(args, "workers", 1) > 1:
        return PipelineWorkers(args.workers, args.threads or 1, **load)
    if args.threads:
        torch.set_num_threads(args.threads)
    return Pipeline.load(**load)


def corner_box(text: str) -> tuple[float, float, float, float]:
    """'x,y,w,h' px -> (x0, y0, x1, y1), the 2D stage's box."""
    try:
        x, y, w, h = (float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"--bbox wants x,y,w,h in px; got {text!r}") from None
    return (x, y, x + w, y + h)


def predict(args) -> int:
    """Streams the sources through the pipeline in batches; a bad source is reported on stderr
    and in predictions.jsonl, and the run goes on."""
    from ds3d.io.predictions import predict as stream_predictions
    from ds3d.io.writers import RunWriter
    from ds3d.pipeline import MIN_SCORE
    from ds3d.util.progress import progress

    pipeline = load_pipeline(args)
    skipped = []
    with (
        RunWriter(args.out, args.json, args.coco, args.overlay, args.stride, args.bvh) as out,
        progress(desc="predict", unit="img") as bar,
    ):

        def skip(frame) -> None:
            skipped.append(frame)
            out.skip(frame)
            bar.write(f"skipped {frame.source}: {frame.error}", file=sys.stderr)

        predictions = stream_predictions(
            args.sources,
            pipeline,
            batch_size=args.batch_size,
            stride=args.stride,
            bbox=None if args.bbox is None else corner_box(args.bbox),
            people=args.people,
            min_score=MIN_SCORE if args.min_score is None else args.min_score,
            iterations=args.iterations,
            focal_px=args.focal_px,
            smooth=not args.no_smooth,
            on_skip=skip,
        )
        try:
            for prediction in predictions:
                out.write(prediction)
                bar.update()
        except KeyboardInterrupt:  # how a webcam run ends: what was estimated is kept
            print("interrupted", file=sys.stderr)
    print(f"{out.count} images, {len(skipped)} skipped: wrote {args.out}/", file=sys.stderr)
    return 0


def gallery(args) -> int:
    """Random picks, not the best ones: the gallery shows successes and failures alike."""
    from ds3d.data.lsp import load_lsp
    from ds3d.evaluation.metrics import pck
    from ds3d.io.images import read_image
    from ds3d.util.progress import progress
    from ds3d.viz.render import render

    pipeline = load_pipeline(args)
    if args.photos is not None:
        return gallery_of_photos(pipeline, args.photos, args.out / "photos")
    ann = load_lsp(split="test")
    picks = sorted(np.random.default_rng(args.seed).choice(len(ann), args.n, replace=False))
    with progress(total=len(picks), desc="gallery", unit="img") as bar:
        images = [read_image(ann.image_paths[i]) for i in picks]
        result = pipeline.estimate(images)  # one batch (the bar waits), then the renders
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
            bar.write(f"{args.out / f'{name}.png'} {caption}")
            bar.update()
    return 0


def gallery_of_photos(pipeline, folder: Path, out: Path) -> int:
    """Every JPEG or PNG photo of `folder` without a box, every person found, one render each."""
    from ds3d.io.images import read_image
    from ds3d.util.progress import progress
    from ds3d.viz.render import render

    out.mkdir(parents=True, exist_ok=True)
    photos = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    with progress(photos, desc="gallery", unit="img") as bar:
        for path in bar:
            image = read_image(path)
            found = pipeline.estimate([image], people="all")
            scores = ", ".join(f"{s:.2f}" for s in found.score.tolist())
            caption = f"{path.name}: {len(found.score)} people found (scores {scores or '-'})"
            render(
                out / f"{path.stem}.png",
                image,
                found.joints_2d.numpy(),
                found.joints_3d.numpy(),
                caption=caption,
                scores=found.score.numpy(),
            )
            bar.write(f"{out / f'{path.stem}.png'} {caption}")
    return 0


def eval_lsp_pipeline(args) -> int:
    """LSP's protocol as the 2D stage's `ds3d eval lsp`: all 14 joints of every image."""
    from ds3d.data.lsp import load_lsp
    from ds3d.pipeline import PipelineConfig

    names = [v for v in args.variants.split(",") if v]
    unknown = set(names) - set(REFINEMENT_VARIANTS)
    if unknown:
        known = ", ".join(REFINEMENT_VARIANTS)
        raise SystemExit(f"unknown variants {sorted(unknown)}; known: {known}")
    overrides = field_overrides(PipelineConfig, args.set)
    pipeline = load_pipeline(args)
    ann = load_lsp(split=args.split)
    ann = ann.subset(range(args.start, len(ann), args.every))
    if args.limit is not None:
        ann = ann.subset(range(min(args.limit, len(ann))))
    results = evaluate_refinement(
        pipeline, ann, names, overrides, args.batch, searched=args.searched
    )
    split = "test im1001-im2000" if args.split == "test" else "train im0001-im1000"
    report = {
        "dataset": f"LSP {split}, images [{args.start}::{args.every}] of the split",
        "n_images": len(ann),
        "threads": args.threads,
        **results,
    }
    write_report(report, args.out)
    return 0


def eval_joint_confidence(args) -> int:
    """ECE and reliability of the raw and the calibrated confidences (the model's calibration,
    or with --fit the one fitted here and written to the model directory)."""
    from ds3d.confidence import FILE_NAME, fit_joint_calibration
    from ds3d.data.lsp import load_lsp
    from ds3d.evaluation.lsp import joint_outcomes
    from ds3d.evaluation.metrics import expected_calibration_error, reliability
    from ds3d.skeleton import JOINT_NAMES
    from ds3d.viz.reliability import plot_reliability

    pipeline = load_pipeline(args)
    ann = load_lsp(split=args.split)
    stop = len(ann) if args.limit is None else min(len(ann), args.start + args.limit)
    ann = ann.subset(range(args.start, stop))
    raw, correct = joint_outcomes(pipeline, ann, args.batch)
    if args.fit:
        pipeline.joint_calibration = fit_joint_calibration(raw, correct)
        pipeline.joint_calibration.save(args.model_dir / "image2d" / FILE_NAME)
    curves = {"raw": raw}
    if pipeline.joint_calibration is not None:
        curves["calibrated"] = pipeline.joint_calibration(raw)
    split = "test im1001-im2000" if args.split == "test" else "train im0001-im1000"
    report = {
        "dataset": f"LSP {split}, images [{args.start}:{stop}] of the split, searched",
        "n_images": len(ann),
        "fitted_here": args.fit,
        "fraction_right": round(float(correct.double().mean()), 4),
        **{
            label: {
                "ece": round(expected_calibration_error(conf, correct), 4),
                "reliability": reliability(conf, correct),
                "per_joint": {
                    name: {
                        "confidence": round(float(conf[:, j].mean()), 4),
                        "fraction_right": round(float(correct[:, j].double().mean()), 4),
                    }
                    for j, name in enumerate(JOINT_NAMES)
                },
            }
            for label, conf in curves.items()
        },
    }
    if args.plot is not None:
        eces = ", ".join(f"{label} ECE {report[label]['ece']:.3f}" for label in curves)
        plot_reliability(
            {label: report[label]["reliability"] for label in curves},
            args.plot,
            f"{report['dataset']}: {eces}",
        )
    write_report(report, args.out)
    return 0


def eval_people(args) -> int:
    """ds3d.evaluation.people's protocol with the pipeline run on whole canvases, no box: every
    person found is scored, the protocol's figures taken at the default min_score."""
    import time

    import cv2

    from ds3d.evaluation.people import calibration, people_of, protocol, score
    from ds3d.pipeline import MIN_SCORE, PipelineConfig
    from ds3d.util.progress import progress

    pipeline = load_pipeline(args)
    pipeline.config = PipelineConfig(**field_overrides(PipelineConfig, args.set))

    def canvases_of(split: str, start: int) -> list:
        return protocol(people_of(split, start), args.count, args.seed, args.empty, args.cut)

    canvases = canvases_of(args.split, args.start)
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
        for i, canvas in enumerate(canvases):
            cv2.imwrite(str(args.save / f"{i:04d}.png"), canvas.image[..., ::-1])
    candidates = _people_candidates(pipeline, canvases, args.batch)
    # The speed as a user meets it: a second pass at the default min_score, which lifts only
    # the people answered (min_score 0 lifts every candidate).
    with progress(total=len(canvases), desc="people, timed", unit="img") as bar:
        start = time.perf_counter()
        for first in range(0, len(canvases), args.batch):
            part = canvases[first : first + args.batch]
            pipeline.estimate([c.image for c in part], people="all")
            bar.update(len(part))
        seconds = time.perf_counter() - start
    answered = [(poses[s >= MIN_SCORE], s[s >= MIN_SCORE]) for poses, s, _ in candidates]
    search = pipeline.config.search
    report = {
        "split": args.split,
        "start": args.start,
        "seed": args.seed,
        "empty": args.empty,
        "cut": args.cut,
        "threads": args.threads,
        "set": args.set,
        "min_score": MIN_SCORE,
        "images_per_s": round(len(canvases) / seconds, 2),
        **score(canvases, answered),
        "calibration": calibration(canvases, candidates, search),
        "by_min_score": {},
    }
    if args.calibrate_also:
        pooled, pooled_candidates = list(canvases), list(candidates)
        for other in args.calibrate_also:
            split, _, start = other.partition(":")
            more = canvases_of(split, int(start or 0))
            pooled += more
            pooled_candidates += _people_candidates(pipeline, more, args.batch)
        report["calibration_pooled"] = {
            "with": args.calibrate_also,
            **calibration(pooled, pooled_candidates, search),
        }
    for threshold in (0.1, 0.2, 0.3, 0.5, 0.7):
        kept = [(poses[s >= threshold], s[s >= threshold]) for poses, s, _ in candidates]
        figures = score(canvases, kept)
        report["by_min_score"][str(threshold)] = {
            "recall": {name: round(b["recall"], 4) for name, b in figures["bins"].items()},
            "precision": round(figures["all"]["precision"], 4),
            "large": {name: round(v, 4) for name, v in figures["large"].items()},
            "answers_on_empty_canvases": figures["answers_on_empty_canvases"],
        }
    if args.plot is not None:
        from ds3d.viz.reliability import plot_reliability

        fit = report["calibration"]
        plot_reliability(
            {"person score": fit["reliability"]},
            args.plot,
            f"people canvases, {args.split} from {args.start}: {fit['candidates']} answers at "
            f"min_score 0, ECE {fit['ece']:.3f}",
            right="fraction that are people",
        )
    write_report(report, args.out)
    return 0


def _people_candidates(pipeline, canvases: list, batch: int) -> list:
    """Per canvas, every person the pipeline answers at min_score 0, `batch` canvases at a
    time: (poses (N, 14, 2) px as answered, scores (N,), their person evidence (N, 3))."""
    from ds3d.util.progress import progress

    candidates = []
    with progress(total=len(canvases), desc="people", unit="img") as bar:
        for first in range(0, len(canvases), batch):
            part = canvases[first : first + batch]
            result = pipeline.estimate([c.image for c in part], people="all", min_score=0.0)
            for i in range(len(part)):
                own = result.rows(torch.nonzero(result.image_index == i).view(-1))
                evidence = own.score_evidence.numpy()
                candidates.append((own.joints_2d.numpy(), own.score.numpy(), evidence))
            bar.update(len(part))
    return candidates
