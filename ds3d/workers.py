"""Whole images of a batch on several worker processes, each with its own Pipeline.

The threads of one process share its interpreter lock, and the 2D stage's Python between its
torch ops holds it for about a fifth of the stage's time (py-spy --gil, one thread): on 2 cores
two threads gave a batch of 16 LSP images 1.2-1.4x the images/s of one, where two processes of
one thread each gave 1.7x (docs/RESULTS.md, worker processes). `PipelineWorkers` starts N
processes, each loading its own Pipeline with T torch threads (about 1 GB each), and splits every
batch into N contiguous parts of whole images, run at once. The processes are spawned, not
forked: torch's and OpenMP's thread pools do not survive a fork.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import torch

from ds3d.pipeline import MIN_SCORE, Pipeline, PipelineConfig
from ds3d.result import PipelineResult

_pipeline: Pipeline | None = None  # a worker process's own (_load)
_everyone = None  # the barrier of all the pool's workers (_load)


class PipelineWorkers:
    """`workers` processes, each a Pipeline.load(**load) with `threads` torch threads; estimate()
    as Pipeline.estimate, its batch split among them, and `config` as Pipeline.config. Close it
    (or use it in a with block) to stop the processes."""

    def __init__(self, workers: int, threads: int = 1, **load: Any):
        if workers < 1 or threads < 1:
            raise ValueError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.workers = workers
        self.config: PipelineConfig = load.get("config", PipelineConfig())
        context = multiprocessing.get_context("spawn")
        everyone = context.Barrier(workers)
        self._pool = ProcessPoolExecutor(
            workers, mp_context=context, initializer=_load, initargs=(threads, load, everyone)
        )
        # Every worker loaded before the first batch, so that its parts start at once: each
        # waits at the barrier until all have loaded and taken one of these.
        for done in [self._pool.submit(_wait) for _ in range(workers)]:
            done.result()

    def estimate(
        self,
        images,
        bboxes: Sequence | None = None,
        intrinsics=None,
        iterations: int | None = None,
        people: str | Sequence[str] = "best",
        min_score: float | Sequence[float] = MIN_SCORE,
        focal_px: float | Sequence[float | None] | None = None,
    ) -> PipelineResult:
        """Pipeline.estimate (the same arguments and result) of the images split into up to
        `workers` contiguous parts, one per process. timings_ms: each stage's milliseconds
        summed over the parts; total, the call's wall time."""
        start = time.perf_counter()
        n = len(images)
        if intrinsics is not None:
            intrinsics = np.asarray(intrinsics, np.float32)
        splits = np.array_split(np.arange(n), max(1, min(self.workers, n)))
        parts = [rows for rows in splits if len(rows)]
        calls = []
        for rows in parts or [np.arange(0)]:
            options = {
                "bboxes": _rows(bboxes, rows, n),
                "intrinsics": intrinsics[rows] if _per_camera(intrinsics) else intrinsics,
                "iterations": iterations,
                "people": _rows(people, rows, n),
                "min_score": _rows(min_score, rows, n),
                "focal_px": _rows(focal_px, rows, n),
            }
            calls.append(self._pool.submit(_estimate, [images[i] for i in rows], options))
        results = [call.result() for call in calls]
        merged = PipelineResult.concat(results, [len(rows) for rows in parts] or [0])
        merged.timings_ms["total"] = round(1000 * (time.perf_counter() - start), 3)
        return merged

    def close(self) -> None:
        self._pool.shutdown()

    def __enter__(self) -> PipelineWorkers:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _per_image(value) -> bool:
    """Whether an option holds one value per image (a sequence) rather than one for all."""
    return value is not None and not isinstance(value, str | int | float)


def _per_camera(intrinsics: np.ndarray | None) -> bool:
    """Whether intrinsics are one (3, 3) matrix per image, (B, 3, 3), rather than one for all."""
    return intrinsics is not None and intrinsics.ndim == 3


def _rows(value, rows: np.ndarray, n: int):
    """A per-image option's values for `rows`; one for all images stays as it is (the pipeline
    checks that a per-image one has n values)."""
    if not _per_image(value):
        return value
    values = list(value)
    if len(values) != n:
        raise ValueError(f"{len(values)} per-image values for {n} images")
    return [values[i] for i in rows]


def _load(threads: int, load: dict, everyone) -> None:
    """A worker's start: its torch threads, its Pipeline, the pool's barrier."""
    global _pipeline, _everyone
    torch.set_num_threads(threads)
    _pipeline, _everyone = Pipeline.load(**load), everyone


def _wait() -> None:
    """Returns once every worker of the pool runs one: all of them have loaded."""
    assert _everyone is not None
    _everyone.wait()


def _estimate(images: list[np.ndarray], options: dict) -> PipelineResult:
    assert _pipeline is not None, "a worker's pipeline is loaded as it starts"
    return _pipeline.estimate(images, **options)
