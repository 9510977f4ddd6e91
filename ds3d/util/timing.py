"""Wall time of the stages of a batched call, as the results report it (timings_ms)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def stage_timer(timings: dict[str, float], stage: str, device: torch.device) -> Iterator[None]:
    """Add the wall time of the block, in ms, to timings[stage]; on CUDA, after the device has
    finished the block's work (kernels run asynchronously)."""
    start = time.perf_counter()
    yield
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    timings[stage] = timings.get(stage, 0.0) + 1000 * (time.perf_counter() - start)
