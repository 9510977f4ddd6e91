"""Whole images of a batch on parallel CPU threads, one intra-op thread each.

Much of the per-image work here (the forests' gathers, small max-convolutions, one image's PSM
at a time) does not parallelise within a torch op, or loses to the threads' overhead on small
tensors; whole images do parallelise. With torch.get_num_threads() = N, a batch is split into N
contiguous parts run at once on N threads of one intra-op thread each.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import numpy as np
import torch

T = TypeVar("T")


@contextmanager
def intra_op_threads(n: int) -> Iterator[None]:
    """torch.set_num_threads(n) for the block, the calling thread's setting restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def split_rows(n: int, device: torch.device | None = None) -> list[torch.Tensor]:
    """Rows 0..n-1 in at most torch.get_num_threads() contiguous, non-empty, ascending parts:
    (n_i,) int64 tensors. For work on a `device` other than the CPU, one part: the device runs
    its kernels in parallel itself, and threads would only contend to launch them."""
    if device is not None and device.type != "cpu":
        return [torch.arange(n)]
    parts = np.array_split(np.arange(n), torch.get_num_threads())
    return [torch.from_numpy(rows) for rows in parts if len(rows)]


def map_on_threads(fn: Callable[[torch.Tensor], T], parts: list[torch.Tensor]) -> list[T]:
    """[fn(rows) for rows in parts], the parts at once on threads of one intra-op thread each
    (a single part runs on the calling thread, with its threads)."""
    if len(parts) == 1:
        return [fn(parts[0])]

    def run(rows: torch.Tensor) -> T:
        with intra_op_threads(1):
            return fn(rows)

    with ThreadPoolExecutor(max_workers=len(parts)) as pool:
        return list(pool.map(run, parts))
