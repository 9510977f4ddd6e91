"""A token bucket of requests per caller (`rate_limit_rps`, bursts of `rate_limit_burst`; a caller
is an API key's id, or the client address when the service runs without keys). Over it a request
gets 429 with Retry-After. With the cap on the items one caller may have waiting in a model queue
(MicroBatcher's max_queue_per_caller, the `caller_queue_share` setting) and the round-robin
batches, one caller cannot starve the others.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

# Buckets of callers idle long enough to be full again are forgotten past this many callers.
MAX_TRACKED_CALLERS = 4096


class TooManyRequests(Exception):
    """A caller is over its share; retry after `retry_after_s` seconds."""

    def __init__(self, message: str, retry_after_s: float):
        super().__init__(message)
        self.retry_after_s = retry_after_s


@dataclass
class _Bucket:
    tokens: float
    stamp: float  # clock() when tokens was computed


class RequestRate:
    """A token bucket per caller: `rate` requests per second on average, `burst` at once."""

    def __init__(self, rate: float, burst: int, clock: Callable[[], float] = time.monotonic):
        self.rate, self.burst, self.clock = rate, burst, clock
        self._buckets: dict[str, _Bucket] = {}

    def take(self, caller: str) -> None:
        """Spend one token of `caller`'s bucket; TooManyRequests when it has none."""
        now = self.clock()
        bucket = self._buckets.get(caller)
        if bucket is None:
            if len(self._buckets) >= MAX_TRACKED_CALLERS:
                self._forget_full(now)
            bucket = self._buckets[caller] = _Bucket(float(self.burst), now)
        bucket.tokens = min(self.burst, bucket.tokens + (now - bucket.stamp) * self.rate)
        bucket.stamp = now
        if bucket.tokens < 1.0:
            wait = (1.0 - bucket.tokens) / self.rate
            raise TooManyRequests(
                f"over rate_limit_rps = {self.rate:g} requests per second for this caller", wait
            )
        bucket.tokens -= 1.0

    def _forget_full(self, now: float) -> None:
        full_after = self.burst / self.rate
        self._buckets = {
            caller: b for caller, b in self._buckets.items() if now - b.stamp < full_after
        }
