"""MicroBatcher over a plain deterministic batch function (squares numbers, refuses negatives)."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from ds3d_service.microbatch import (
    BatchStats,
    CallerQueueFull,
    DeadlineExceeded,
    ItemFailed,
    MicroBatcher,
    QueueFull,
    ShuttingDown,
)


class Squares:
    """Squares a batch of numbers; a negative number fails the whole batch (like a model that
    validates its input). Records the batches it saw; `gate` can hold it to fill the queue."""

    def __init__(self):
        self.batches: list[list[float]] = []
        self.gate = threading.Event()
        self.gate.set()

    def __call__(self, xs):
        self.gate.wait(5)
        self.batches.append(list(xs))
        if any(x < 0 for x in xs):
            raise ValueError("negative input")
        return [x * x for x in xs]


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 20))


def make(fn, stats=None, **kw):
    params = dict(max_batch_size=8, max_wait_s=0.05, max_queue=64)
    params.update(kw)
    on_batch = stats.append if stats is not None else None
    return MicroBatcher(fn, executor=ThreadPoolExecutor(1), on_batch=on_batch, **params)


def test_concurrent_items_share_batches_and_get_their_own_results():
    fn, stats = Squares(), []

    async def main():
        b = make(fn, stats, max_batch_size=8, max_wait_s=0.2)
        b.start()
        out = await asyncio.gather(*(b.submit(float(i), 5) for i in range(20)))
        await b.close(5)
        return out

    assert run(main()) == [float(i * i) for i in range(20)]
    sizes = [len(batch) for batch in fn.batches]
    assert sum(sizes) == 20
    assert max(sizes) == 8  # filled to max_batch_size, never beyond
    assert [s.size for s in stats] == sizes
    assert all(isinstance(s, BatchStats) and s.seconds >= 0 for s in stats)


def test_batches_take_items_round_robin_across_callers():
    """A caller with 24 items queued does not hold back another caller's one item: it goes out
    in the next batch, and the first caller keeps its own order."""
    fn = Squares()
    fn.gate.clear()  # hold the first batch so that the queue fills

    async def main():
        b = make(fn, max_batch_size=4, max_wait_s=0.0)
        b.start()
        greedy = asyncio.ensure_future(b.submit_many([float(i) for i in range(24)], 5, "key:a"))
        await asyncio.sleep(0.1)  # the worker took the first batch and waits on the gate
        polite = asyncio.ensure_future(b.submit(100.0, 5, "key:b"))
        await asyncio.sleep(0.05)
        fn.gate.set()
        out = await asyncio.gather(greedy, polite)
        await b.close(5)
        return out

    greedy, polite = run(main())
    assert polite == 10_000.0 and greedy == [float(i * i) for i in range(24)]
    assert fn.batches[0] == [0.0, 1.0, 2.0, 3.0]
    assert fn.batches[1] == [4.0, 100.0, 5.0, 6.0]  # one item each in turn, then a's remain
    assert [x for batch in fn.batches for x in batch] == [0, 1, 2, 3, 4, 100, *range(5, 24)]


def test_a_caller_waits_with_at_most_its_share_of_the_queue():
    fn = Squares()
    fn.gate.clear()

    async def main():
        b = make(fn, max_batch_size=2, max_wait_s=0.0, max_queue=16, max_queue_per_caller=6)
        b.start()
        first = asyncio.ensure_future(b.submit_many([1.0, 2.0], 5, "key:a"))  # taken, running
        await asyncio.sleep(0.1)
        waiting = asyncio.ensure_future(b.submit_many([3.0] * 6, 5, "key:a"))
        await asyncio.sleep(0.05)
        with pytest.raises(CallerQueueFull, match="limit is 6"):
            await b.submit(4.0, 5, "key:a")
        other = asyncio.ensure_future(b.submit_many([5.0] * 6, 5, "key:b"))  # b's own share
        await asyncio.sleep(0.05)
        fn.gate.set()
        out = await asyncio.gather(first, waiting, other)
        await b.close(5)
        return out

    first, waiting, other = run(main())
    assert first == [1.0, 4.0] and waiting == [9.0] * 6 and other == [25.0] * 6


def test_a_lone_item_leaves_after_max_wait():
    fn = Squares()

    async def main():
        b = make(fn, max_batch_size=64, max_wait_s=0.05)
        b.start()
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        y = await b.submit(3.0, 5)
        waited = loop.time() - t0
        await b.close(5)
        return y, waited

    y, waited = run(main())
    assert y == 9.0
    assert 0.04 <= waited < 2.0


def test_a_bad_item_fails_alone():
    fn = Squares()

    async def main():
        b = make(fn, max_batch_size=8, max_wait_s=0.2)
        b.start()
        tasks = [b.submit(x, 5) for x in (1.0, 2.0, -1.0, 4.0)]
        out = await asyncio.gather(*tasks, return_exceptions=True)
        await b.close(5)
        return out

    out = run(main())
    assert out[0] == 1.0 and out[1] == 4.0 and out[3] == 16.0
    assert isinstance(out[2], ValueError)
    assert len(fn.batches[0]) == 4  # they were batched together first


def test_submit_many_reports_the_failing_index():
    fn = Squares()

    async def main():
        b = make(fn)
        b.start()
        try:
            await b.submit_many([1.0, -2.0, 3.0], 5)
        finally:
            await b.close(5)

    with pytest.raises(ItemFailed) as info:
        run(main())
    assert info.value.index == 1 and isinstance(info.value.cause, ValueError)


def test_full_queue_refuses_at_once():
    fn = Squares()
    fn.gate.clear()

    async def main():
        b = make(fn, max_batch_size=1, max_wait_s=0.0, max_queue=2)
        b.start()
        first = asyncio.ensure_future(b.submit(1.0, 5))
        await asyncio.sleep(0.05)  # the worker holds item 1 (blocked on the gate)
        queued = [asyncio.ensure_future(b.submit(x, 5)) for x in (2.0, 3.0)]
        await asyncio.sleep(0.01)
        assert b.depth == 2 and b.saturated
        with pytest.raises(QueueFull):
            await b.submit(4.0, 5)
        with pytest.raises(QueueFull):  # all-or-nothing for a multi-item request
            await b.submit_many([5.0, 6.0], 5)
        fn.gate.set()
        out = await asyncio.gather(first, *queued)
        await b.close(5)
        return out

    assert run(main()) == [1.0, 4.0, 9.0]


def test_deadline_passes_while_waiting():
    fn = Squares()
    fn.gate.clear()

    async def main():
        b = make(fn, max_batch_size=1, max_wait_s=0.0)
        b.start()
        slow = asyncio.ensure_future(b.submit(1.0, 5))
        await asyncio.sleep(0.05)
        with pytest.raises(DeadlineExceeded):
            await b.submit(2.0, 0.1)
        fn.gate.set()
        assert await slow == 1.0
        await b.close(5)

    run(main())
    # The expired item was dropped from the queue without being computed.
    assert fn.batches == [[1.0]]


def test_close_drains_the_queue_then_refuses():
    fn = Squares()
    fn.gate.clear()

    async def main():
        b = make(fn, max_batch_size=2, max_wait_s=0.0)
        b.start()
        tasks = [asyncio.ensure_future(b.submit(float(x), 5)) for x in range(5)]
        await asyncio.sleep(0.05)
        closing = asyncio.ensure_future(b.close(5))
        await asyncio.sleep(0.01)
        with pytest.raises(ShuttingDown):
            await b.submit(9.0, 5)
        fn.gate.set()
        await closing
        return await asyncio.gather(*tasks)

    assert run(main()) == [0.0, 1.0, 4.0, 9.0, 16.0]


def test_an_item_that_cannot_make_its_deadline_is_not_computed():
    fn, stats = Squares(), []

    def slow(xs):
        time.sleep(0.3)
        return fn(xs)

    async def main():
        b = make(slow, stats, max_batch_size=1, max_wait_s=0.0)
        b.start()
        assert await b.submit(1.0, 5) == 1.0  # teaches the batcher that a batch takes ~0.3 s
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(DeadlineExceeded):
            await b.submit(2.0, 0.2)
        waited = loop.time() - t0
        await b.close(5)
        return waited

    waited = run(main())
    assert waited < 0.15  # refused at pick-up, not at the deadline
    assert fn.batches == [[1.0]]
    assert sum(s.dropped for s in stats) == 1
