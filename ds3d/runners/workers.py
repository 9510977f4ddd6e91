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
import signal
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import torch

from ds3d.inputs import MIN_SCORE, ImageInput, image_inputs
from ds3d.pipeline import Pipeline
from ds3d.result import PipelineResult

_pipeline: Pipeline | None = None  # a worker process's own (_load)
_everyone = None  # the barrier of all the pool's workers (_load)


class PipelineWorkers:
    """`workers` processes, each a Pipeline.load(**load) with `threads` torch threads; estimate()
    and run() as the Pipeline's, each batch split among them. Close it (or use it in a with
    block) to stop the processes."""

    def __init__(self, workers: int, threads: int = 1, **load: Any):
        if workers < 1 or threads < 1:
            raise ValueError(f"workers and threads must be >= 1, got {workers} and {threads}")
        self.workers = workers
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
        """Pipeline.estimate (the same arguments and result), its images checked here and run
        by the workers (run)."""
        checked = image_inputs(images, bboxes, intrinsics, focal_px, people, min_score)
        return self.run(checked, iterations)

    def run(self, inputs: Sequence[ImageInput], iterations: int | None = None) -> PipelineResult:
        """Pipeline.run of checked images split into up to `workers` contiguous parts, one per
        process. timings_ms: each stage's milliseconds summed over the parts; total, the call's
        wall time."""
        start = time.perf_counter()
        splits = np.array_split(np.arange(len(inputs)), max(1, min(self.workers, len(inputs))))
        parts = [rows for rows in splits if len(rows)] or [np.arange(0)]
        calls = [self._pool.submit(_run, [inputs[i] for i in rows], iterations) for rows in parts]
        results = [call.result() for call in calls]
        first_images = [int(rows[0]) if len(rows) else 0 for rows in parts]
        merged = PipelineResult.concat(results, first_images)
        merged.timings_ms["total"] = round(1000 * (time.perf_counter() - start), 3)
        return merged

    def close(self) -> None:
        self._pool.shutdown()

    def __enter__(self) -> PipelineWorkers:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _load(threads: int, load: dict, everyone) -> None:
    """A worker's start: its torch threads, its Pipeline, the pool's barrier. Ctrl+C reaches
    the whole process group: a worker leaves it to its parent, which stops the pool (close),
    rather than die with a traceback while the parent shuts down in order."""
    global _pipeline, _everyone
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(threads)
    _pipeline, _everyone = Pipeline.load(**load), everyone


def _wait() -> None:
    """Returns once every worker of the pool runs one: all of them have loaded."""
    assert _everyone is not None
    _everyone.wait()


def _run(inputs: list[ImageInput], iterations: int | None) -> PipelineResult:
    assert _pipeline is not None, "a worker's pipeline is loaded as it starts"
    return _pipeline.run(inputs, iterations)
