"""The 3D stage's commands: `ds3d lift` (2D poses in a JSON file to 3D) and `ds3d eval h36m`."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from ds3d.cli.parser import (
    add_model_options,
    add_set_option,
    field_overrides,
    set_threads,
    write_report,
)
from ds3d.skeleton import BONE_NAMES

LIFTER_OVERRIDE = "override a LifterConfig field (ds3d.lifter), e.g. proportions=false or "
LIFTER_OVERRIDE += "omega.proportions=1; repeatable"


def register(commands, evals, benches) -> None:
    p = commands.add_parser("lift", help="lift 2D poses (JSON) to 3D")
    p.add_argument(
        "input",
        type=Path,
        help='JSON: {"joints_2d": [[[x, y] x 14], ...], '
        '"intrinsics": optional, "visible": optional}',
    )
    p.add_argument("--out", type=Path, help="result JSON (default: stdout)")
    add_model_options(p, threads=None, device=True)
    add_set_option(p, LIFTER_OVERRIDE)
    p.set_defaults(func=lift)

    p = evals.add_parser("h36m", help="Human3.6M protocol with ground-truth 2D (S11)")
    p.add_argument("--subject", default="S11", help="test subject (S9 for tuning on training data)")
    p.add_argument("--stride", type=int, default=64, help="every n-th frame of each sequence")
    p.add_argument("--limit", type=int, help="evaluate only the first n test poses")
    p.add_argument(
        "--proportions",
        metavar="GROUP=SCALE,...",
        help="the test subject's bone groups rescaled, e.g. "
        "pelvis=0.5,thigh=1.1,shin=1.1,upper_arm=0.9,head=1.3 (groups: ds3d.skeleton.BONE_GROUPS)",
    )
    p.add_argument(
        "--variants",
        default="clean,noise5,noise10,outlier40,every-set,unweighted",
        help="comma-separated input/algorithm variants (ds3d.evaluation.h36m.VARIANTS)",
    )
    p.add_argument(
        "--video",
        action="store_true",
        help="instead: sequences as 2D tracks with --noise px, jitter and error before and after "
        "the video smoothing (ds3d.evaluation.h36m.video_report)",
    )
    p.add_argument("--noise", type=float, default=10.0, help="px, with --video")
    p.add_argument("--out", type=Path, help="JSON report")
    add_model_options(p, threads=None, device=True)
    add_set_option(p, LIFTER_OVERRIDE)
    p.set_defaults(func=eval_h36m)


def load_lifter(args):
    """The Lifter of --model-dir/--database on --device, configured by --set."""
    from ds3d.lifter import Lifter, LifterConfig

    set_threads(args)
    overrides = field_overrides(LifterConfig, getattr(args, "set", []))
    config = dataclasses.replace(LifterConfig(), **overrides)
    return Lifter.load(args.model_dir, args.device, config, args.database)


def lift(args) -> int:
    request = json.loads(args.input.read_text())
    lifter = load_lifter(args)
    result = lifter.lift(request["joints_2d"], request.get("visible"), request.get("intrinsics"))
    write_report(
        {
            "model": lifter.model_id,
            # rounded in float64: a rounded float32 prints as -135.7100067138672
            "joints_3d": result.joints_3d.double().numpy().round(2).tolist(),
            "bone_names": list(BONE_NAMES),
            "bone_lengths": result.bone_lengths.double().numpy().round(1).tolist(),
            "joint_set": result.joint_set,
            "energy": result.energy.tolist(),
            **(
                {}
                if result.root_position is None
                else {"root_position": result.root_position.double().numpy().round(1).tolist()}
            ),
            "timings_ms": result.timings_ms,
        },
        args.out,
    )
    return 0


def eval_h36m(args) -> int:
    from ds3d.evaluation.h36m import VARIANTS, evaluate_variant, protocol_cases, video_report

    if args.video:
        lifter = load_lifter(args)
        report = {"model": lifter.model_id, "database": args.database}
        report |= video_report(lifter, args.subject, args.noise)
        raw, smoothed = report["raw"], report["smoothed"]
        print(
            f"jitter {raw['jitter']:.1f} -> {smoothed['jitter']:.1f} mm/frame^2, camera-space "
            f"MPJPE {raw['camera_mpjpe']:.1f} -> {smoothed['camera_mpjpe']:.1f} mm, MPJPE "
            f"{raw['mpjpe']:.1f} -> {smoothed['mpjpe']:.1f} mm ({report['frames']} frames)",
            file=sys.stderr,
        )
        write_report(report, args.out)
        return 0

    names = args.variants.split(",")
    unknown = set(names) - set(VARIANTS)
    if unknown:
        raise SystemExit(f"unknown variants {sorted(unknown)}; known: {', '.join(VARIANTS)}")
    proportions = dict(
        (name, float(value))
        for name, _, value in (item.partition("=") for item in (args.proportions or "").split(","))
        if name
    )
    try:
        cases = protocol_cases(args.subject, args.stride, proportions)
    except ValueError as err:
        raise SystemExit(f"--proportions: {err}") from None
    if args.limit:
        cases = cases.subset(np.arange(min(args.limit, len(cases))))
    lifter = load_lifter(args)
    base = lifter.config
    report = {
        "model": lifter.model_id,
        "database": args.database,
        "subject": args.subject,
        "stride": args.stride,
        "proportions": proportions,
        "variants": {},
    }
    for name in names:
        result = evaluate_variant(lifter, cases, name, base)
        report["variants"][name] = result
        print(
            f"{name:>28}: 3D pose error {result['pose_error']:.1f} mm, PA-MPJPE "
            f"{result['pa_mpjpe']:.1f}, MPJPE {result['mpjpe']:.1f}; placed in the camera: MRPE "
            f"{result['mrpe']:.1f}, MPJPE {result['camera_mpjpe']:.1f} ({result['frames']} "
            f"poses, {result['seconds']} s)",
            file=sys.stderr,
        )
    write_report(report, args.out)
    return 0
