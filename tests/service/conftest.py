"""The service tests' models and servers: the bundled models loaded once, and `serving`, which
runs an app around them under a real uvicorn on a free port of 127.0.0.1 (in a thread)."""

from __future__ import annotations

import socket
import threading
import time
from contextlib import contextmanager

import pytest
import uvicorn

from ds3d.util.paths import MODELS_DIR
from ds3d_service.app import create_app
from ds3d_service.engine import Engine
from ds3d_service.settings import Settings
from tests.needs import missing

# The model the service would serve: $DS3D_MODEL_DIR, else the bundled models/.
MODEL_DIR = Settings().model_dir or MODELS_DIR


@contextmanager
def serve(engine: Engine, **settings):
    """A uvicorn server for create_app(Settings(**settings), engine) on a free port; its URL."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    app = create_app(Settings(port=port, **settings), engine)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "server did not start"
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(30)
        sock.close()


@pytest.fixture(scope="session")
def serving():
    """serving(engine, **settings): a context manager serving create_app(Settings(**settings),
    engine); it yields the server's URL."""
    return serve


@pytest.fixture(scope="session")
def engine():
    """The bundled models (or $DS3D_MODEL_DIR's), loaded once for every service test."""
    if not (MODEL_DIR / "posedb").exists():
        missing(f"no pose database under {MODEL_DIR}")
    return Engine.load(MODEL_DIR, "cpu")


@pytest.fixture(scope="session")
def pose_engine(model_dir):
    """Models with a 2D stage (tests/conftest.py's model_dir: a --small 2D model beside the
    bundled pose database), so that /v1/pose runs the real Pipeline."""
    engine = Engine.load(model_dir, "cpu")
    assert engine.pipeline is not None, engine.pose_unavailable
    return engine
