"""The models behind the service and their batch functions (run on the one model thread).

`Engine.lift_batch` and `Engine.pose_batch` take a list of per-request items, checked where they
entered (ds3d.inputs), and return one output per item, in order, with the library call it ran in;
they are the `run_batch` functions of the MicroBatchers.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from ds3d.errors import DataFormatError
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.inputs import ImageInput, PoseInput
from ds3d.lifter import LiftedPose, Lifter
from ds3d.pipeline import Pipeline
from ds3d.result import Person
from ds3d.runners.workers import PipelineWorkers
from ds3d.util.paths import MODELS_DIR


@dataclass(frozen=True)
class BatchInfo:
    """The library call an item ran in: an id (to sum stage times once per call), its size and
    its per-stage times."""

    call_id: int
    size: int
    timings_ms: dict[str, float]


@dataclass(frozen=True)
class LiftOutput:
    pose: LiftedPose
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

    def lift_batch(self, items: Sequence[PoseInput]) -> list[LiftOutput]:
        """3D poses of B checked 2D poses (ds3d.inputs.pose_input)."""
        res = self.lifter.run(items)
        info = self._batch_info(len(items), res.timings_ms)
        return [LiftOutput(res.pose(i), info) for i in range(len(items))]

    def pose_batch(self, items: Sequence[ImageInput]) -> list[PoseOutput]:
        """2D and 3D poses of B checked images (ds3d.inputs.image_input; needs the pipeline),
        each image's people as its item asks: the pipeline lifts only them."""
        if self.pipeline is None:
            raise RuntimeError(self.pose_unavailable)
        res = self.pipeline.run(items)
        info = self._batch_info(len(items), res.timings_ms)
        return [PoseOutput(res.people(i), info) for i in range(len(items))]
