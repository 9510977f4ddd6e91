"""`python -m service` (console script `ds3d-serve`): run the HTTP service with uvicorn.

Settings come from DS3D_* env vars (service/settings.py); the flags below override them.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ds3d-serve", description=__doc__.splitlines()[0])
    parser.add_argument("--host", help="bind address (DS3D_HOST, default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port (DS3D_PORT, default 8000)")
    parser.add_argument("--model-dir", type=Path, help="model directory (DS3D_MODEL_DIR)")
    parser.add_argument("--max-batch-size", type=int, help="DS3D_MAX_BATCH_SIZE")
    parser.add_argument("--max-wait-ms", type=float, help="DS3D_MAX_WAIT_MS")
    parser.add_argument("--torch-threads", type=int, help="DS3D_TORCH_THREADS")
    args = parser.parse_args(argv)
    from service.settings import Settings

    settings = Settings(**{k: v for k, v in vars(args).items() if v is not None})
    # Before torch loads: keep OpenMP to the configured threads too.
    os.environ.setdefault("OMP_NUM_THREADS", str(settings.torch_threads))

    import uvicorn

    from service.app import create_app

    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(name)s %(message)s")
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        # Let in-flight requests finish (they are bounded by the request timeout).
        timeout_graceful_shutdown=int(settings.request_timeout_s) + 5,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
