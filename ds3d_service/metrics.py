"""Prometheus metrics of one app instance (its own registry, so that several apps, as in the
tests, do not collide): requests by route and status, latency, queue depth, batch sizes and
per-stage model time, and the process's own (memory, open files, CPU time, allocator)."""

from __future__ import annotations

from collections.abc import Callable

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    ProcessCollector,
    generate_latest,
)

from ds3d.util.memory import loaded_allocator, tree_resident_mb
from ds3d_service.microbatch import BatchStats

LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256)


class Metrics:
    def __init__(self):
        self.registry = CollectorRegistry()
        # the process's memory, open files and CPU time (process_*; Linux), which a soak watches
        ProcessCollector(registry=self.registry)
        # ... and with its worker processes (DS3D_WORKERS), whose memory a soak watches too
        Gauge(
            "ds3d_resident_memory_bytes",
            "Resident memory of the server process and its worker processes (Linux)",
            registry=self.registry,
        ).set_function(lambda: tree_resident_mb() * 2**20)
        Info("ds3d_allocator", "The process's memory allocator", registry=self.registry).info(
            {"name": loaded_allocator()}
        )
        self.requests = Counter(
            "ds3d_requests",
            "HTTP requests answered, by route template and status code",
            ["route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "ds3d_request_latency_seconds",
            "Time from request to response, by route template",
            ["route"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.queue_depth = Gauge(
            "ds3d_queue_depth",
            "Items waiting for a batch, by queue",
            ["queue"],
            registry=self.registry,
        )
        self.queue_wait = Histogram(
            "ds3d_queue_wait_seconds",
            "Time an item waited before its batch started, by queue",
            ["queue"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.batch_size = Histogram(
            "ds3d_batch_size",
            "Items per model call, by queue",
            ["queue"],
            buckets=BATCH_BUCKETS,
            registry=self.registry,
        )
        self.batch_seconds = Histogram(
            "ds3d_batch_seconds",
            "Time of one model call (a whole batch), by queue",
            ["queue"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )
        self.dropped = Counter(
            "ds3d_deadline_dropped_items",
            "Items not computed because their deadline had passed or would pass first, by queue",
            ["queue"],
            registry=self.registry,
        )
        self.stage_seconds = Histogram(
            "ds3d_stage_seconds",
            "Model time per stage, one observation per batch",
            ["stage"],
            buckets=LATENCY_BUCKETS_S,
            registry=self.registry,
        )

    def observe_request(self, route: str, status: int, seconds: float) -> None:
        self.requests.labels(route, str(status)).inc()
        self.latency.labels(route).observe(seconds)

    def batch_observer(self, queue: str) -> Callable[[BatchStats], None]:
        """An on_batch callback for the MicroBatcher of `queue`."""

        def observe(stats: BatchStats) -> None:
            self.dropped.labels(queue).inc(stats.dropped)
            if stats.size == 0:
                return
            self.batch_size.labels(queue).observe(stats.size)
            self.batch_seconds.labels(queue).observe(stats.seconds)
            for wait in stats.queue_wait_s:
                self.queue_wait.labels(queue).observe(wait)

        return observe

    def observe_stages(self, timings_ms: dict[str, float]) -> None:
        for stage, ms in timings_ms.items():
            self.stage_seconds.labels(stage).observe(ms / 1000.0)

    def render(self) -> bytes:
        return generate_latest(self.registry)
