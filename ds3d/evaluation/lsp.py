"""LSP's 2D protocol: PCK@0.2 (torso = mean of the two shoulder-hip diagonals) per joint and
mean, and mean pixel error, over all 14 joints of every image (occluded joints included; on
LSPet, which places only the joints it sees, over those, in the images where a diagonal's two
ends are placed, the torso then the mean of such diagonals), for
the 2D stage (evaluate_2d) and for the 3D stage's 2D refinement and its ablation, the paper's
fig:query (evaluate_refinement); and how often the answered joints are right at each confidence
(joint_outcomes, for ds3d.confidence).
"""

from __future__ import annotations

import dataclasses
import time

import torch

from ds3d.data.lsp import PoseAnnotations
from ds3d.evaluation.metrics import (
    expected_calibration_error,
    pck,
    pixel_error,
    reliability,
    torso_diameter,
)
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.result import Estimate2D
from ds3d.io.images import read_image
from ds3d.lifter import UNWEIGHTED_OVERRIDES, LifterConfig
from ds3d.pipeline import Pipeline, PipelineConfig
from ds3d.skeleton import JOINT_NAMES
from ds3d.util.progress import progress

# The refinement's variants: the paper's fig:query protocol (one iteration, K = 256 without
# weighting, eq:energyS on all of them) and the full method (K = 128 -> K_w weighted,
# PipelineConfig's iterations), as (PipelineConfig fields, LifterConfig fields).
REFINEMENT_VARIANTS: dict[str, tuple[dict, dict]] = {
    "full": ({}, {}),
    "all-only": ({"iterations": 1}, {"joint_sets": ("all",), **UNWEIGHTED_OVERRIDES}),
    "energy": ({"iterations": 1, "selection": "energy"}, UNWEIGHTED_OVERRIDES),
    "posterior": ({"iterations": 1}, UNWEIGHTED_OVERRIDES),
}


def pck_report(
    pred: torch.Tensor, gt: torch.Tensor, located: torch.Tensor, per_joint: bool = False
) -> dict:
    """pred, gt: (N, 14, 2) px, located: (N, 14) bool, the joints placed and scored, each image
    with a torso diagonal placed -> PCK@0.2 (and per joint) and the mean pixel error."""
    joint_pck = pck(pred, gt, located, reference=torso_diameter(gt, located))
    report: dict[str, float | dict[str, float]] = {"pck@0.2": round(float(joint_pck.mean()), 4)}
    if per_joint:
        report["pck@0.2_per_joint"] = {
            n: round(float(v), 4) for n, v in zip(JOINT_NAMES, joint_pck, strict=True)
        }
    report["mean_pixel_error"] = round(float(pixel_error(pred, gt, located).mean()), 2)
    return report


def argmax_joints(res: Estimate2D) -> torch.Tensor:
    """No PSM: per joint, the best cell of the returned unaries (the forests', plus the joint
    network's where the model has one). (B, 14, 2) px."""
    b, j, _, w = res.unaries.shape
    best = res.unaries.reshape(b, j, -1).argmax(-1)
    uv1 = torch.stack([best % w, best // w, torch.ones_like(best)], -1).float()
    return torch.einsum("bij,bkj->bki", res.map_to_image, uv1)


def evaluate_2d(est: PoseEstimator2D, ann: PoseAnnotations, batch: int = 16) -> dict:
    """The protocol for the 2D stage: the full model (pyramid + PSM) and the unaries alone
    (argmax_joints: the argmax of each joint's unary map at the scale the PSM chose, with its
    left/right decision)."""
    preds, argmax = [], []
    t0 = time.perf_counter()
    with progress(total=len(ann), desc="lsp", unit="img") as bar:
        for i in range(0, len(ann), batch):
            images = [read_image(p) for p in ann.image_paths[i : i + batch]]
            res = est.estimate(images)
            preds.append(res.joints_2d.cpu())  # from the estimator's device
            argmax.append(argmax_joints(res).cpu())
            bar.update(len(images))
    seconds = time.perf_counter() - t0
    scored = with_torso(ann)
    out: dict[str, float | dict] = {"n_images": int(scored.sum()), "seconds": round(seconds, 1)}
    if not scored.all():
        out["n_images_without_torso"] = int((~scored).sum())
    for name, pred in (("psm", torch.cat(preds)), ("unary_argmax", torch.cat(argmax))):
        out[name] = scored_report(pred, ann, per_joint=True)
    return out


def with_torso(ann: PoseAnnotations) -> torch.Tensor:
    """(N,) bool: the images where both ends of a torso diagonal are placed (PCK's reference)."""
    return torso_diameter(ann.joints, ann.located).isfinite()


def scored_report(pred: torch.Tensor, ann: PoseAnnotations, per_joint: bool = False) -> dict:
    """pck_report of pred (N, 14, 2) px on the images of ann with_torso, over their placed
    joints."""
    scored = with_torso(ann)
    gt, located = torch.from_numpy(ann.joints)[scored], torch.from_numpy(ann.located)[scored]
    return pck_report(pred[scored], gt, located, per_joint)


def variant_configs(name: str, overrides: dict) -> tuple[PipelineConfig, LifterConfig]:
    """The configurations of one of REFINEMENT_VARIANTS, with PipelineConfig field overrides."""
    config, lifter_config = REFINEMENT_VARIANTS[name]
    return PipelineConfig(**(config | overrides)), LifterConfig(**lifter_config)


def describe_variant(config: PipelineConfig, lifter_config: LifterConfig) -> dict:
    keep = ("neighbours", "weighted_neighbours", "weighting", "joint_sets")
    return dataclasses.asdict(config) | {k: getattr(lifter_config, k) for k in keep}


def evaluate_refinement(
    pipeline: Pipeline,
    ann: PoseAnnotations,
    names: list[str],
    overrides: dict | None = None,
    batch: int = 16,
    searched: bool = False,
) -> dict:
    """The protocol for the 2D pose after each iteration of each of REFINEMENT_VARIANTS
    `names` (with PipelineConfig field `overrides`), beside the 2D stage's ("initial"), all
    from one 2D estimate per image. searched: also the pipeline as a user without a box runs
    it ("searched": the best person the search finds, ds3d.people.search), what the tight
    crops' own box is worth. Leaves the pipeline configured as the last variant.
    Returns {"variants", "seconds", "results"}."""
    overrides = overrides or {}
    preds: dict[str, list[torch.Tensor]] = {"initial": []}
    seconds = dict.fromkeys(["2d", *names, *(["searched"] if searched else [])], 0.0)
    with progress(total=len(ann), desc="lsp-pipeline", unit="img") as bar:
        for start in range(0, len(ann), batch):
            images = [read_image(p) for p in ann.image_paths[start : start + batch]]
            if searched:
                t0 = time.perf_counter()
                pipeline.config, lifter_config = variant_configs("full", overrides)
                pipeline.lifter.configure(lifter_config)
                preds.setdefault("searched", []).append(pipeline.estimate(images).joints_2d)
                seconds["searched"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            estimate = pipeline.estimator.estimate(images)
            seconds["2d"] += time.perf_counter() - t0
            preds["initial"].append(estimate.joints_2d.cpu())
            for name in names:
                t0 = time.perf_counter()
                pipeline.config, lifter_config = variant_configs(name, overrides)
                pipeline.lifter.configure(lifter_config)
                res = pipeline.lift_estimate(estimate)
                for t in range(res.iterations):
                    preds.setdefault(f"{name}/iteration{t + 1}", []).append(
                        res.joints_2d_iterations[:, t]
                    )
                seconds[name] += time.perf_counter() - t0
            bar.update(len(images))
    return {
        "variants": {n: describe_variant(*variant_configs(n, overrides)) for n in names},
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "results": {k: scored_report(torch.cat(v).cpu(), ann) for k, v in preds.items()},
    }


def joint_outcomes(
    pipeline: Pipeline, ann: PoseAnnotations, batch: int = 16, threshold: float = 0.2
) -> tuple[torch.Tensor, torch.Tensor]:
    """The pipeline as a user without a box runs it (each image searched, its best person) on
    the images of `ann`: the 2D stage's raw probability at each answered joint (the confidence
    without the pipeline's JointCalibration) and whether the joint lies within `threshold`
    times the torso diameter of the truth (PCK's test). Returns (N, 14) float32, (N, 14) bool."""
    calibration, pipeline.joint_calibration = pipeline.joint_calibration, None
    raw, joints = [], []
    try:
        with progress(total=len(ann), desc="joint outcomes", unit="img") as bar:
            for start in range(0, len(ann), batch):
                images = [read_image(p) for p in ann.image_paths[start : start + batch]]
                result = pipeline.estimate(images)
                raw.append(result.confidence)
                joints.append(result.joints_2d)
                bar.update(len(images))
    finally:
        pipeline.joint_calibration = calibration
    gt = torch.from_numpy(ann.joints).float()
    correct = (torch.cat(joints) - gt).norm(dim=-1) <= threshold * torso_diameter(gt)[:, None]
    return torch.cat(raw), correct


def confidence_report(raw: torch.Tensor, correct: torch.Tensor, calibration=None) -> dict:
    """How well confidences say how often joints are right, from joint_outcomes (raw (N, 14),
    correct (N, 14)): the fraction right and, for the raw confidences and those of
    `calibration` (a ds3d.confidence.JointCalibration) where given, the expected calibration
    error, the reliability bins and each joint's mean confidence against its fraction right."""
    curves = {"raw": raw} | ({} if calibration is None else {"calibrated": calibration(raw)})
    return {
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
