"""The per-caller token bucket (ds3d_service/access/ratelimit.py), on a fake clock."""

from __future__ import annotations

import pytest

from ds3d_service.access.ratelimit import RequestRate, TooManyRequests


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_bucket_allows_a_burst_then_the_rate_and_keeps_callers_apart():
    clock = Clock()
    rate = RequestRate(rate=2.0, burst=3, clock=clock)
    for _ in range(3):
        rate.take("key:a")
    with pytest.raises(TooManyRequests) as info:
        rate.take("key:a")
    assert info.value.retry_after_s == pytest.approx(0.5)  # one token at 2 per second
    assert "rate_limit_rps = 2" in str(info.value)
    rate.take("key:b")  # another caller has its own bucket
    clock.now += 0.5
    rate.take("key:a")  # refilled one
    with pytest.raises(TooManyRequests):
        rate.take("key:a")
    clock.now += 60
    for _ in range(3):  # refilled to the burst, not beyond
        rate.take("key:a")
    with pytest.raises(TooManyRequests):
        rate.take("key:a")
