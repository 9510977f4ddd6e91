"""The models behind the service and their batch functions (run on the one model thread).

`Engine.lift_batch` and `Engine.pose_batch` take a list of per-request items and return one
output per item, in order; they are the `run_batch` functions of the MicroBatchers. Items with
and without intrinsics are run as separate library calls, because the library takes intrinsics
for the whole batch or not at all.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ds3d.errors import DataFormatError
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.search import check_searchable
from ds3d.inputs import focal_length, intrinsics_batch, joints_2d_batch, visibility_batch
from ds3d.lifter import Lifter
from ds3d.pipeline import MIN_SCORE, Pipeline
from ds3d.result import Person
from ds3d.util.groups import group_rows
from ds3d.util.paths import MODELS_DIR
from ds3d.workers import PipelineWorkers


@dataclass(frozen=True)
class LiftInput:
    joints_2d: np.ndarray  # (14, 2) float32, pixels
    visible: np.ndarray  # (14,) bool
    intrinsics: np.ndarray | None  # (3, 3) float32, or None when unknown


@dataclass(frozen=True)
class PoseInput:
    image: np.ndarray  # (H, W, 3) uint8
    bbox: np.ndarray | None  # (4,) float32 x0, y0, x1, y1 pixels
    intrinsics: np.ndarray | None  # (3, 3) float32
    people: str = "best"  # ds3d.pipeline.PEOPLE
    min_score: float = MIN_SCORE
    focal_px: float | None = None  # without intrinsics; None: an assumed camera


@dataclass(frozen=True)
class BatchInfo:
    """The library call an item ran in: an id (to sum stage times once per call), its size and
    its per-stage times."""

    call_id: int
    size: int
    timings_ms: dict[str, float]


@dataclass(frozen=True)
class LiftOutput:
    joints_3d: np.ndarray  # (14, 3) float32, mm
    bone_lengths: np.ndarray  # (14,) float32, mm, ds3d.skeleton.BONE_NAMES order
    joint_set: str
    energy: float
    root_position: np.ndarray | None  # (3,) float32 mm in the camera's coordinates (intrinsics)
    batch: BatchInfo


@dataclass(frozen=True)
class PoseOutput:
    people: list[Person]  # best first; exactly one with people="best"
    batch: BatchInfo


def request_timings_ms(
    outputs: Sequence[LiftOutput | PoseOutput], total_s: float
) -> dict[str, float]:
    """A request's timings: per-stage ms summed over the distinct library calls its outputs ran
    in (items that shared a call count it once), plus the request's total."""
    stages: dict[str, float] = {}
    for info in {o.batch.call_id: o.batch for o in outputs}.values():
        for stage, ms in info.timings_ms.items():
            stages[stage] = stages.get(stage, 0.0) + ms
    stages["total"] = total_s * 1000.0
    return stages


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _stacked_intrinsics(intrinsics: list[np.ndarray | None]) -> np.ndarray | None:
    """The intrinsics of a group of items that all carry one or none (group_rows), (B, 3, 3) or
    None."""
    given = [k for k in intrinsics if k is not None]
    return np.stack(given) if given else None


def load_pipeline(model_dir: Path | None, device: str) -> tuple[Pipeline | None, str | None]:
    """The image -> 2D + 3D Pipeline of model_dir, or (None, why) when it has no 2D stage."""
    try:
        return Pipeline.load(model_dir=model_dir, device=device), None
    except (DataFormatError, FileNotFoundError) as e:
        return None, f"the model directory has no usable 2D stage: {e}"


def missing_2d_stage(model_dir: Path | None) -> str | None:
    """Why model_dir (None: the bundled models/) has no usable 2D stage, or None when it has."""
    try:
        PoseEstimator2D.load((model_dir or MODELS_DIR) / "image2d")
    except (DataFormatError, FileNotFoundError) as e:
        return f"the model directory has no usable 2D stage: {e}"
    return None


class Engine:
    """The loaded models. `on_timings(timings_ms)`, when set, is called once per library call
    (the app points it at its metrics). `pipeline`: a Pipeline, or a PipelineWorkers whose
    processes split each /v1/pose batch; close() stops those."""

    def __init__(
        self,
        lifter: Lifter,
        pipeline: Pipeline | PipelineWorkers | None = None,
        pose_unavailable: str | None = None,
    ):
        self.lifter = lifter
        self.pipeline = pipeline
        self.pose_unavailable = pose_unavailable if pipeline is None else None
        self.on_timings: Callable[[dict[str, float]], None] | None = None
        self._call_ids = itertools.count()

    @classmethod
    def load(
        cls, model_dir: Path | None, device: str = "cpu", workers: int = 1, threads: int = 1
    ) -> Engine:
        """The models of model_dir (None: the bundled models/). /v1/lift needs its pose database;
        /v1/pose also its 2D stage. With one worker the pipeline's lifter serves /v1/lift too
        (loaded once); with more, /v1/pose runs on a PipelineWorkers of `workers` processes of
        `threads` torch threads, and /v1/lift on a lifter of this process."""
        if workers == 1:
            pipeline, why = load_pipeline(model_dir, device)
            lifter = (
                pipeline.lifter if pipeline is not None else Lifter.load(model_dir, device=device)
            )
            return cls(lifter, pipeline, why)
        lifter = Lifter.load(model_dir, device=device)
        if why := missing_2d_stage(model_dir):
            return cls(lifter, None, why)
        return cls(lifter, PipelineWorkers(workers, threads, model_dir=model_dir, device=device))

    def close(self) -> None:
        """Stops the pipeline's worker processes, where it has them."""
        if isinstance(self.pipeline, PipelineWorkers):
            self.pipeline.close()

    @property
    def model_id(self) -> str:
        return self.lifter.model_id

    def _batch_info(self, size: int, timings_ms: dict[str, float]) -> BatchInfo:
        timings = {k: float(v) for k, v in timings_ms.items()}
        if self.on_timings is not None:
            self.on_timings(timings)
        return BatchInfo(next(self._call_ids), size, timings)

    def lift_batch(self, items: Sequence[LiftInput]) -> list[LiftOutput]:
        """3D poses of B 2D poses; raises ds3d.errors.InvalidPose when the library refuses one."""
        out: list[LiftOutput | None] = [None] * len(items)
        for idx in group_rows(it.intrinsics is not None for it in items).values():
            joints = np.stack([items[i].joints_2d for i in idx])
            visible = np.stack([items[i].visible for i in idx])
            intrinsics = _stacked_intrinsics([items[i].intrinsics for i in idx])
            res = self.lifter.lift(joints, visible=visible, intrinsics=intrinsics)
            info = self._batch_info(len(idx), res.timings_ms)
            joints_3d, bones = _numpy(res.joints_3d), _numpy(res.bone_lengths)
            energy = _numpy(res.energy)
            roots = None if res.root_position is None else _numpy(res.root_position)
            for j, i in enumerate(idx):
                out[i] = LiftOutput(
                    joints_3d[j],
                    bones[j],
                    res.joint_set[j],
                    float(energy[j]),
                    None if roots is None else roots[j],
                    info,
                )
        return out  # type: ignore[return-value]

    def check_pose_input(self, item: PoseInput) -> None:
        """The library's own checks of an image's inputs, made before it is queued, so that a
        bad one is refused at once and never fails a batch: InvalidPose for intrinsics or a
        focal length that are not a camera's, InvalidImage for an image too elongated to search
        for people."""
        if item.intrinsics is not None:
            intrinsics_batch(item.intrinsics, 1)
        if item.focal_px is not None:
            focal_length(item.focal_px)
        if item.bbox is None and self.pipeline is not None:
            height, width = item.image.shape[:2]
            check_searchable(height, width, self.pipeline.config.search)

    def check_lift_input(self, item: LiftInput) -> None:
        """The library's own checks of a 2D pose, made before it is queued (InvalidPose)."""
        joints_2d_batch(item.joints_2d)
        visibility_batch(item.visible, 1)
        intrinsics_batch(item.intrinsics, 1)

    def pose_batch(self, items: Sequence[PoseInput]) -> list[PoseOutput]:
        """2D and 3D poses of B images (needs the pipeline; a box may be None per image, the
        intrinsics are given for a whole call or not at all), each image's people as its item
        asks (people, min_score): the pipeline lifts only them."""
        if self.pipeline is None:
            raise RuntimeError(self.pose_unavailable)
        out: list[PoseOutput | None] = [None] * len(items)
        for idx in group_rows(it.intrinsics is not None for it in items).values():
            boxes = [items[i].bbox for i in idx]
            res = self.pipeline.estimate(
                [items[i].image for i in idx],
                bboxes=None if all(b is None for b in boxes) else boxes,
                intrinsics=_stacked_intrinsics([items[i].intrinsics for i in idx]),
                people=[items[i].people for i in idx],
                min_score=[items[i].min_score for i in idx],
                focal_px=[items[i].focal_px for i in idx],
            )
            info = self._batch_info(len(idx), res.timings_ms)
            for j, i in enumerate(idx):
                out[i] = PoseOutput(res.people(j), info)
        return out  # type: ignore[return-value]
