"""The pipeline's evaluations: `ds3d eval lsp-pipeline` (the refinement on LSP), `ds3d eval
joint-confidence` (how often joints are right at each confidence; --fit calibrates) and `ds3d eval
people` (people of any size on canvases; --fit fits the person score). The reports are built by
ds3d.evaluation; here they are parsed for and written."""

from __future__ import annotations

import os
from pathlib import Path

from ds3d.cli.parser import (
    add_model_options,
    add_set_option,
    field_overrides,
    load_pipeline,
    write_report,
)
from ds3d.evaluation.lsp import REFINEMENT_VARIANTS

SPLITS = {"test": "test im1001-im2000", "train": "train im0001-im1000"}


def register(commands, evals, benches) -> None:
    variants = ",".join(REFINEMENT_VARIANTS)
    p = evals.add_parser(
        "lsp-pipeline", help="2D accuracy of the refinement (iterations, joint-set ablation) on LSP"
    )
    p.add_argument("--split", choices=tuple(SPLITS), default="test")
    p.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    p.add_argument("--every", type=int, default=1, help="every n-th image of the split")
    p.add_argument("--limit", type=int, help="at most this many images (after --every)")
    p.add_argument("--variants", default=variants, help=f"of {variants}")
    p.add_argument("--batch", type=int, default=16)
    add_set_option(p, "a PipelineConfig field in every variant (e.g. refine.min_var=4)")
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
    p.add_argument("--split", choices=tuple(SPLITS), default="test")
    p.add_argument("--start", type=int, default=0, help="skip the split's first n images")
    p.add_argument("--limit", type=int, help="at most this many images")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--fit", action="store_true", help="fit and write the calibration")
    p.add_argument("--plot", type=Path, help="also the reliability diagram as a PNG")
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, threads=min(2, os.cpu_count() or 1))
    p.set_defaults(func=eval_joint_confidence)

    p = evals.add_parser(
        "people",
        help="people of any size in 640x480 canvases built from LSP: detection and PCK",
        description="--fit fits the person score on these canvases (with --calibrate-also's) "
        "and writes it beside the 2D model (MODEL_DIR/image2d/person_score.json), refitting "
        "under the new score until it stays; fit on held-out people (--split train --start "
        "700) only.",
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
    p.add_argument("--fit", action="store_true", help="fit and write the person score")
    p.add_argument("--plot", type=Path, help="also the person score's reliability diagram, a PNG")
    p.add_argument("--out", type=Path, help="JSON report")
    add_set_option(p, "a PipelineConfig field (e.g. search.proposal_floor=110)")
    add_model_options(p)
    p.set_defaults(func=eval_people)


def eval_lsp_pipeline(args) -> int:
    """LSP's protocol as the 2D stage's `ds3d eval lsp`: all 14 joints of every image."""
    from ds3d.data.lsp import load_lsp
    from ds3d.evaluation.lsp import evaluate_refinement
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
    report = {
        "dataset": f"LSP {SPLITS[args.split]}, images [{args.start}::{args.every}] of the split",
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
    from ds3d.evaluation.lsp import confidence_report, joint_outcomes
    from ds3d.viz.reliability import plot_reliability

    pipeline = load_pipeline(args)
    ann = load_lsp(split=args.split)
    stop = len(ann) if args.limit is None else min(len(ann), args.start + args.limit)
    ann = ann.subset(range(args.start, stop))
    raw, correct = joint_outcomes(pipeline, ann, args.batch)
    if args.fit:
        pipeline.joint_calibration = fit_joint_calibration(raw, correct)
        pipeline.joint_calibration.save(args.model_dir / "image2d" / FILE_NAME)
    report = {
        "dataset": f"LSP {SPLITS[args.split]}, images [{args.start}:{stop}] of the split, searched",
        "n_images": len(ann),
        "fitted_here": args.fit,
        **confidence_report(raw, correct, pipeline.joint_calibration),
    }
    if args.plot is not None:
        curves = [label for label in ("raw", "calibrated") if label in report]
        eces = ", ".join(f"{label} ECE {report[label]['ece']:.3f}" for label in curves)
        plot_reliability(
            {label: report[label]["reliability"] for label in curves},
            args.plot,
            f"{report['dataset']}: {eces}",
        )
    write_report(report, args.out)
    return 0


# Refitting the person score under the last fit settles within a few rounds: the candidates it
# fits change only where the score reorders the same-person suppression.
FIT_ROUNDS = 3


def eval_people(args) -> int:
    """ds3d.evaluation.people's protocol with the pipeline run on whole canvases, no box: every
    person found is scored, the protocol's figures taken at the default min_score; with --fit,
    the person score fitted on them (and --calibrate-also's) and written to the model."""
    import dataclasses

    import cv2

    from ds3d.evaluation.canvases import people_of, protocol
    from ds3d.evaluation.people import calibration, candidates_of, people_report
    from ds3d.people.score import PersonScore
    from ds3d.pipeline import PipelineConfig

    pipeline = load_pipeline(args, PipelineConfig(**field_overrides(PipelineConfig, args.set)))
    floor = pipeline.config.search.proposal_floor
    if pipeline.person_score is None and args.fit:  # a start: the PSM score alone orders them
        pipeline.person_score = PersonScore(0.0, 1.0, 0.0, 0.0, floor)

    def canvases_of(split: str, start: int) -> list:
        return protocol(people_of(split, start), args.count, args.seed, args.empty, args.cut)

    canvases = canvases_of(args.split, args.start)
    pooled = list(canvases)
    for other in args.calibrate_also:
        split, _, start = other.partition(":")
        pooled += canvases_of(split, int(start or 0))
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
        for i, canvas in enumerate(canvases):
            cv2.imwrite(str(args.save / f"{i:04d}.png"), canvas.image[..., ::-1])
    candidates = candidates_of(pipeline, pooled, args.batch)
    for _ in range(FIT_ROUNDS if args.fit else 0):
        fitted = PersonScore(**calibration(pooled, candidates, floor)["person_score"])
        if fitted == pipeline.person_score:
            break
        pipeline.person_score = fitted
        candidates = candidates_of(pipeline, pooled, args.batch)
    if args.fit:
        assert pipeline.person_score is not None
        pipeline.person_score.save(args.model_dir / "image2d")
    own = candidates[: len(canvases)]
    report = {
        "split": args.split,
        "start": args.start,
        "seed": args.seed,
        "empty": args.empty,
        "cut": args.cut,
        "threads": args.threads,
        "set": args.set,
        "person_score": None
        if pipeline.person_score is None
        else dataclasses.asdict(pipeline.person_score),
        "fitted_here": args.fit,
        **people_report(pipeline, canvases, own, args.batch),
    }
    if args.calibrate_also:
        report["calibration_pooled"] = {
            "with": args.calibrate_also,
            **calibration(pooled, candidates, floor),
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
