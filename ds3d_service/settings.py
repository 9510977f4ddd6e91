"""The service's configuration: one pydantic-settings object read from `DS3D_*` env vars.

Each field's description is its documentation: `ds3d-serve --help` shows it as the help of the
field's flag (ds3d_service/__main__.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from ds3d.util.machine import default_threads, default_workers


def workers_for(settings: dict) -> int:
    """The workers setting's default, from the settings read before it (device):
    ds3d.util.machine.default_workers."""
    return default_workers(settings["device"])


def threads_for(settings: dict) -> int:
    """The torch_threads setting's default, from the settings read before it (workers):
    ds3d.util.machine.default_threads."""
    return default_threads(settings["workers"])


class Settings(BaseSettings):
    """Every knob of the service; each field `x` is read from the env var `DS3D_X`."""

    model_config = SettingsConfigDict(env_prefix="DS3D_", frozen=True)

    host: str = Field("127.0.0.1", description="Address to bind.")
    port: int = Field(8000, ge=0, le=65535, description="Port to listen on.")
    model_dir: Path | None = Field(
        None, description="Model directory; unset: the models/ directory bundled with the package."
    )
    device: str = Field("cpu", description="Torch device the models run on.")
    max_wait_ms: float = Field(
        5.0,
        ge=0.0,
        description="Micro-batching, one queue per endpoint: a batch closes when it holds its "
        "batch size of items or when its oldest item has waited this many milliseconds, "
        "whichever comes first.",
    )
    max_batch_size: int = Field(
        16,
        ge=1,
        le=4096,
        description="Batch size of /v1/pose, in images (20-25 per second on two cores).",
    )
    max_queue: int = Field(
        64,
        ge=1,
        description="Images (items, not requests) allowed to wait in the /v1/pose queue: past "
        "it a request gets 503 at once. Keep queue / throughput below request_timeout_s, or "
        "the overflow waits for a 504 instead of getting a quick 503 (docs/service-results.md, "
        "overload).",
    )
    max_lift_batch_size: int = Field(
        64,
        ge=1,
        le=4096,
        description="Batch size of /v1/lift, in 2D poses (several hundred per second).",
    )
    max_lift_queue: int = Field(
        512,
        ge=1,
        description="2D poses (items, not requests) allowed to wait in the /v1/lift queue: past "
        "it a request gets 503 at once. Keep queue / throughput below request_timeout_s, as "
        "for max_queue.",
    )
    request_timeout_s: float = Field(
        10.0,
        gt=0.0,
        description="Seconds after its arrival at which a request not yet answered gets 504.",
    )
    ready_stall_s: float = Field(
        30.0,
        gt=0.0,
        description="Seconds the model worker may hold work (a batch running, or items "
        "waiting) without finishing a batch before /readyz answers 503 stalled, so that no "
        "more traffic is sent to it.",
    )
    live_stall_s: float = Field(
        300.0,
        gt=0.0,
        description="Seconds of the same before /healthz answers 503 too, so that a supervisor "
        "restarts the replica (a thread stuck in a batch cannot be stopped from within). Well "
        "above the longest batch: max_batch_size images of the slowest kind.",
    )
    workers: int = Field(
        default_factory=workers_for,
        ge=1,
        le=64,
        description="Processes of /v1/pose's pipeline, each its own models (about 0.8 GB) with "
        "torch_threads threads, that split each batch (ds3d.runners.workers). On a CPU, "
        "processes give more images/s than as many threads (docs/service-results.md, worker "
        "processes). 1: the pipeline runs on the model thread itself. Default: one per usable "
        "core (the CPU affinity within a container's quota), as many as the available memory "
        "holds beside the service's own (ds3d.util.machine.WORKER_MB, MAIN_MB); 1 on a "
        "GPU.",
    )
    torch_threads: int = Field(
        default_factory=threads_for,
        ge=1,
        description="torch.set_num_threads of each process's model thread: the 2D stage splits "
        "each batch across that many threads, the 3D stage's ops use them within. Default: the "
        "usable cores shared among the workers, at most 2 each (a third thread pays little: "
        "docs/tuning.md, service).",
    )
    max_image_bytes: int = Field(
        10 * 1024 * 1024,
        ge=1,
        description="Largest image upload to /v1/pose, in bytes; a larger one gets 413.",
    )
    max_image_pixels: int = Field(
        40_000_000,
        ge=1,
        description="Largest image to decode, in pixels (width x height, read from its header); "
        "a larger one gets 422. (An image searched for people must also be at most "
        "ds3d.people.search.SearchParams.max_aspect_ratio times as long as wide, else 422.)",
    )
    max_lift_items: int = Field(
        256, ge=1, description="Upper bound of items in one /v1/lift request."
    )
    max_connections: int = Field(
        1024,
        ge=1,
        description="Connections uvicorn serves at once (its limit_concurrency); past it a new "
        "request gets 503 from uvicorn, before the queues see it.",
    )
    keep_alive_s: float = Field(
        5.0, gt=0.0, description="Seconds an idle keep-alive connection stays open (uvicorn)."
    )
    max_header_bytes: int = Field(
        16 * 1024,
        ge=1024,
        description="Largest request head (request line and headers) in bytes; a larger one "
        "gets 431 (and past 4 times this, uvicorn stops reading it with a bare 400).",
    )
    retry_after_s: int = Field(
        1, ge=0, description="Seconds a 503 tells the client to wait before retrying (Retry-After)."
    )
    log_level: str = Field(
        "info", description="Log level of the service and uvicorn (e.g. debug, info, warning)."
    )
    api_keys: SecretStr | None = Field(
        None,
        description="API keys, comma-separated or the path of a file of one key per line (# "
        "comments), each at least 16 characters. When set, /v1/* (and /metrics unless "
        "metrics_public) need `Authorization: Bearer KEY` or `X-API-Key: KEY`, else 401. "
        "Unset: every caller that can reach the service may use it.",
    )
    require_api_keys: bool = Field(
        False,
        description="Refuse to start without api_keys (the Docker image sets it, so that a "
        "deployment is closed unless it is given keys).",
    )
    metrics_public: bool = Field(
        False, description="Serve /metrics without a key when api_keys is set."
    )
    rate_limit_rps: float = Field(
        0.0,
        ge=0.0,
        description="Requests per second one caller (its key; without keys, its address) may "
        "send to /v1/* on average (a token bucket); past it 429 with Retry-After. 0: no limit.",
    )
    rate_limit_burst: int = Field(
        20, ge=1, description="Requests one caller may send at once above rate_limit_rps."
    )
    caller_queue_share: float = Field(
        0.5,
        gt=0.0,
        le=1.0,
        description="Share of each model queue (max_queue, max_lift_queue) one caller may have "
        "waiting; past it 429 with Retry-After while other callers still get in. Batches take "
        "items round-robin across callers.",
    )
    cors_origins: str = Field(
        "",
        description="Origins allowed to call the API from a browser page (CORS), "
        "comma-separated, e.g. https://app.example.org; empty: none (the service's own page "
        "needs none).",
    )
    allocator: Literal["jemalloc", "system"] = Field(
        "jemalloc",
        description="Memory allocator of `ds3d-serve`: jemalloc when installed (Debian: "
        "libjemalloc2), which keeps the resident memory flat; system: the C library's malloc, "
        "whose resident memory grows with the image sizes served (ds3d_service/allocator.py).",
    )
