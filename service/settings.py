"""The service's configuration: one pydantic-settings object read from `DS3D_*` env vars."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Every knob of the service; each field `x` is read from the env var `DS3D_X`."""

    model_config = SettingsConfigDict(env_prefix="DS3D_", frozen=True)

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    # None: the models/ directory bundled with the package.
    model_dir: Path | None = None
    device: str = "cpu"
    # Micro-batching, one queue per endpoint: a batch closes when it holds its batch size of
    # items or when its oldest item has waited max_wait_ms, whichever comes first. Items (not
    # requests) allowed to wait: past the queue's bound a request gets 503 at once. Keep
    # queue / throughput below request_timeout_s, or the overflow waits for a 504 instead of
    # getting a quick 503 (docs/RESULTS.md, service).
    max_wait_ms: float = Field(5.0, ge=0.0)
    # /v1/pose: images (20-25 per second on two cores)
    max_batch_size: int = Field(16, ge=1, le=4096)
    max_queue: int = Field(64, ge=1)
    # /v1/lift: 2D poses (several hundred per second)
    max_lift_batch_size: int = Field(64, ge=1, le=4096)
    max_lift_queue: int = Field(512, ge=1)
    # A request not answered this long after it arrived gets 504.
    request_timeout_s: float = Field(10.0, gt=0.0)
    # torch.set_num_threads of the one model thread: the 2D stage splits each batch across
    # that many threads, the 3D stage's ops use them within. Two pay on two cores for one
    # process (docs/RESULTS.md); replicas, one per core, set 1 (docker/docker-compose.yml).
    torch_threads: int = Field(default_factory=lambda: min(2, os.cpu_count() or 1), ge=1)
    max_image_bytes: int = Field(10 * 1024 * 1024, ge=1)
    max_image_pixels: int = Field(40_000_000, ge=1)
    # Upper bound of items in one /v1/lift request.
    max_lift_items: int = Field(256, ge=1)
    # Seconds a 503 tells the client to wait before retrying (Retry-After).
    retry_after_s: int = Field(1, ge=0)
    log_level: str = "info"
