"""Micro-batching: requests wait in a bounded queue; one worker task forms batches and runs the
batch function on an executor, off the event loop.

A batch closes when it holds `max_batch_size` items, or when its oldest item has waited
`max_wait_s` (timed from that item's arrival, so items that queued while the worker was busy go
out at once). Items are queued per caller and batches take them round-robin across callers, one
item each in turn: a caller with one request waiting gets into the next batch however many items
another caller has queued.

Items whose request has given up, or that would be answered only after their deadline (judged
by the smoothed time of recent batches), are dropped with DeadlineExceeded instead of being
computed: under overload the worker spends its time on answers still wanted.

Each item gets its own outcome: when the batch function raises, the items of that batch are run
again one by one, so that one bad item fails alone and its neighbours still get their results.
Whatever the batch function raises (an Exception or not: SystemExit, KeyboardInterrupt), its
items fail and the worker goes on. `stalled_s` says how long the worker has had work without
finishing a batch, so that health checks can tell a worker stuck on one batch.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")

log = logging.getLogger("ds3d_service")


class QueueError(Exception):
    """Base of what a model queue's submit raises of its own (the service answers each)."""


class QueueFull(QueueError):
    """The queue cannot take the items of this request now; retry later."""


class CallerQueueFull(QueueError):
    """This caller already has its share of the queue waiting; retry later."""


class DeadlineExceeded(QueueError):
    """The request was not answered before its deadline."""


class ShuttingDown(QueueError):
    """The batcher is closing and takes no new work."""


class BatchFailed(RuntimeError):
    """The batch function raised something that is not an Exception; `__cause__` is it."""


class ProgressClock:
    """How long a queue has had work (items waiting or running) without finishing any:
    monotonic seconds, 0 while the queue keeps up or is idle."""

    def __init__(self) -> None:
        self._since: float | None = None  # when the work not yet finished began waiting

    def work_arrived(self) -> None:
        if self._since is None:
            self._since = time.monotonic()

    def progressed(self, more_work: bool) -> None:
        """A batch (or item) finished; `more_work`: others still wait or run."""
        self._since = time.monotonic() if more_work else None

    @property
    def stalled_s(self) -> float:
        return 0.0 if self._since is None else time.monotonic() - self._since


class ItemFailed(QueueError):
    """The batch function failed on item `index` of a request; `__cause__` says why."""

    def __init__(self, index: int, cause: BaseException):
        super().__init__(f"item {index}: {cause}")
        self.index = index
        self.cause = cause


def admit(
    count: int,
    *,
    closing: bool,
    depth: int,
    max_queue: int,
    waiting: int,
    max_queue_per_caller: int | None,
) -> None:
    """The admission checks of a model queue, for a request of `count` items from a caller who
    has `waiting` items queued, while the queue holds `depth`: ShuttingDown when it is
    `closing`, QueueFull when the items do not all fit in max_queue, CallerQueueFull when the
    caller has items waiting and these would take it over max_queue_per_caller (None: no limit
    but the queue's; a request that alone is larger goes in when the caller has none waiting)."""
    if closing:
        raise ShuttingDown("the service is shutting down")
    if depth + count > max_queue:
        raise QueueFull(f"{depth} items queued, limit {max_queue}")
    cap = max_queue_per_caller
    if cap is not None and waiting and waiting + count > cap:
        raise CallerQueueFull(f"{waiting} items of this caller wait, its limit is {cap}")


async def first_result(results: Awaitable[list[R]]) -> R:
    """The result of a one-item submit_many; a failed item raises what it failed with
    (ItemFailed's cause), every other error as it is."""
    try:
        return (await results)[0]
    except ItemFailed as e:
        raise e.cause from None


@dataclass
class _Job(Generic[T, R]):
    item: T
    future: asyncio.Future[R]
    enqueued: float  # loop.time() at arrival
    deadline: float  # loop.time() after which nobody waits for the result


@dataclass
class _Failed:
    """An item's outcome when the batch function raised on it (else its result)."""

    error: Exception


@dataclass
class BatchStats:
    """What the worker reports after each batch: its size, the seconds the batch function took
    (all of its calls, the one-by-one reruns included), each item's wait, and how many items it
    dropped for their deadline (a report with size 0 when it dropped items and ran nothing)."""

    size: int
    seconds: float
    queue_wait_s: list[float] = field(default_factory=list)
    dropped: int = 0  # items dropped for their deadline while this batch was formed


class MicroBatcher(Generic[T, R]):
    """Batches items submitted from the event loop.

    run_batch: a function mapping a list of B items to a list of B results, in order. It runs on
    `executor` (give a single-thread executor so that the model never runs concurrently).
    on_batch: called on the event loop after every batch with its BatchStats (for metrics).
    """

    def __init__(
        self,
        run_batch: Callable[[Sequence[T]], Sequence[R]],
        *,
        executor: Executor,
        max_batch_size: int,
        max_wait_s: float,
        max_queue: int,
        max_queue_per_caller: int | None = None,
        on_batch: Callable[[BatchStats], None] | None = None,
    ):
        if max_batch_size < 1 or max_queue < 1 or max_wait_s < 0:
            raise ValueError("max_batch_size and max_queue must be >= 1, max_wait_s >= 0")
        if max_queue_per_caller is not None and max_queue_per_caller < 1:
            raise ValueError("max_queue_per_caller must be >= 1")
        self._run_batch = run_batch
        self._executor = executor
        self.max_batch_size = max_batch_size
        self.max_wait_s = max_wait_s
        self.max_queue = max_queue
        self.max_queue_per_caller = max_queue_per_caller  # None: no limit but the queue's
        self._on_batch = on_batch
        # per caller, in round-robin order: the caller served next comes first
        self._pending: dict[str, collections.deque[_Job[T, R]]] = {}
        self._depth = 0
        self._wakeup = asyncio.Event()
        self._closing = False
        self._batch_estimate_s = 0.0
        self._worker: asyncio.Task[None] | None = None
        self._clock = ProgressClock()

    @property
    def depth(self) -> int:
        """Items waiting for a batch (not counting the batch being run)."""
        return self._depth

    @property
    def saturated(self) -> bool:
        return self._depth >= self.max_queue

    @property
    def running(self) -> bool:
        return self._worker is not None and not self._worker.done() and not self._closing

    @property
    def closing(self) -> bool:
        """close() was called: the worker finishes what is queued and stops."""
        return self._closing

    @property
    def stalled_s(self) -> float:
        """Seconds the worker has had items waiting or running without finishing a batch."""
        return self._clock.stalled_s

    def start(self) -> None:
        """Start the worker task on the running event loop."""
        if self._worker is None:
            self._worker = asyncio.get_running_loop().create_task(self._work())

    async def submit(self, item: T, timeout_s: float, caller: str = "") -> R:
        """One item's result; raises what submit_many raises (ItemFailed's cause for a bad item)."""
        return await first_result(self.submit_many([item], timeout_s, caller))

    async def submit_many(self, items: Sequence[T], timeout_s: float, caller: str = "") -> list[R]:
        """Queue all items at once (or none) in `caller`'s queue and wait for their results, in
        order.

        Raises what `admit` raises (QueueFull, CallerQueueFull; ShuttingDown after close() or
        before start()), DeadlineExceeded when they are not all done within timeout_s,
        ItemFailed for the first item that failed.
        """
        admit(
            len(items),
            closing=self._closing or self._worker is None,
            depth=self._depth,
            max_queue=self.max_queue,
            waiting=len(self._pending.get(caller, ())),
            max_queue_per_caller=self.max_queue_per_caller,
        )
        loop = asyncio.get_running_loop()
        now = loop.time()
        jobs = [_Job(item, loop.create_future(), now, now + timeout_s) for item in items]
        self._pending.setdefault(caller, collections.deque()).extend(jobs)
        self._depth += len(jobs)
        self._clock.work_arrived()
        self._wakeup.set()
        futures = [job.future for job in jobs]
        _, not_done = await asyncio.wait(futures, timeout=timeout_s)
        if not_done:
            # Cancelled futures are skipped by the worker, so abandoned work is not computed.
            for fut in futures:
                fut.cancel()
            raise DeadlineExceeded(f"not answered within {timeout_s:g} s")
        for i, fut in enumerate(futures):
            if (error := fut.exception()) is not None:
                raise ItemFailed(i, error)
        return [fut.result() for fut in futures]

    async def close(self, drain_timeout_s: float) -> None:
        """Take no new work, finish what is queued (within drain_timeout_s), stop the worker."""
        self._closing = True
        self._wakeup.set()
        if self._worker is None:
            return
        try:
            await asyncio.wait_for(asyncio.shield(self._worker), drain_timeout_s)
        except TimeoutError:
            self._worker.cancel()
            while self._depth:
                job = self._pop()
                if not job.future.done():
                    job.future.set_exception(ShuttingDown("the service shut down"))

    def _pop(self) -> _Job[T, R]:
        """The next item, round-robin: the first caller's oldest, that caller then moved to the
        back of the round."""
        caller, jobs = next(iter(self._pending.items()))
        job = jobs.popleft()
        del self._pending[caller]
        if jobs:
            self._pending[caller] = jobs
        self._depth -= 1
        return job

    async def _work(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            if not self._pending:
                if self._closing:
                    return
                self._wakeup.clear()
                await self._wakeup.wait()
                continue
            oldest = min(jobs[0].enqueued for jobs in self._pending.values())
            flush_at = oldest + self.max_wait_s
            while self._depth < self.max_batch_size and not self._closing:
                remaining = flush_at - loop.time()
                if remaining <= 0:
                    break
                self._wakeup.clear()
                try:
                    await asyncio.wait_for(self._wakeup.wait(), remaining)
                except TimeoutError:
                    break
            now = loop.time()
            live: list[_Job[T, R]] = []
            dropped = 0
            while self._depth and len(live) < self.max_batch_size:
                job = self._pop()
                if job.future.done():  # its request gave up (deadline) already
                    dropped += 1
                elif now + self._batch_estimate_s >= job.deadline:
                    # It would be answered after its request gave up: computing it would only
                    # slow down the items behind it.
                    job.future.set_exception(
                        DeadlineExceeded("would not finish before its deadline")
                    )
                    dropped += 1
                else:
                    live.append(job)
            if live:
                await self._run(live, now, dropped)
            elif dropped:
                self._report(BatchStats(0, 0.0, [], dropped))
            self._clock.progressed(more_work=self._depth > 0)

    async def _run(self, jobs: list[_Job[T, R]], started: float, dropped: int) -> None:
        loop = asyncio.get_running_loop()
        t0 = time.perf_counter()
        try:
            results = await self._call(loop, [j.item for j in jobs])
            if len(results) != len(jobs):
                raise RuntimeError(f"batch function gave {len(results)} results for {len(jobs)}")
            outcomes: list[R | _Failed] = list(results)
        except Exception as batch_error:
            if len(jobs) == 1:
                outcomes = [_Failed(batch_error)]
            else:
                outcomes = [await self._run_one(loop, job.item) for job in jobs]
        seconds = time.perf_counter() - t0
        # Smoothed batch time: how long an item picked now will take at least to be answered.
        self._batch_estimate_s = (
            seconds
            if self._batch_estimate_s == 0.0
            else 0.7 * self._batch_estimate_s + 0.3 * seconds
        )
        for job, outcome in zip(jobs, outcomes, strict=True):
            if job.future.done():
                continue
            if isinstance(outcome, _Failed):
                job.future.set_exception(outcome.error)
            else:
                job.future.set_result(outcome)
        self._report(BatchStats(len(jobs), seconds, [started - j.enqueued for j in jobs], dropped))

    async def _call(self, loop: asyncio.AbstractEventLoop, items: list[T]) -> Sequence[R]:
        """The batch function on the executor; what is not an Exception raised as BatchFailed,
        so that it fails these items and not the worker."""
        try:
            return await loop.run_in_executor(self._executor, self._run_batch, items)
        except (Exception, asyncio.CancelledError):  # cancelled: the worker itself, at close
            raise
        except BaseException as error:
            raise BatchFailed(f"the batch failed: {type(error).__name__}: {error}") from error

    async def _run_one(self, loop: asyncio.AbstractEventLoop, item: T) -> R | _Failed:
        try:
            (result,) = await self._call(loop, [item])
            return result
        except Exception as e:
            return _Failed(e)

    def _report(self, stats: BatchStats) -> None:
        """on_batch(stats); a failing observer is logged, not let through to the worker."""
        if self._on_batch is None:
            return
        try:
            self._on_batch(stats)
        except Exception:
            log.exception("the batch observer failed")
