"""Shared fixtures. Tests that need the datasets skip when $DS3D_DATA is absent, and fail under CI
(tests/needs.py), which has them."""

from __future__ import annotations

import pytest
import torch

from ds3d.util.paths import MODELS_DIR, data_root
from tests.needs import missing


def pytest_configure(config):
    torch.set_num_threads(2)


@pytest.fixture(scope="session")
def data_dir():
    root = data_root()
    if not root.is_dir():
        missing(f"datasets not found at {root} (set DS3D_DATA)")
    return root


@pytest.fixture(scope="module")
def one_thread():
    """torch on one intra-op thread for the module's tests (then as before). The accuracy floors
    measure the same figures on 1 and 2 threads, and one is the quickest on a machine whose
    cores other work shares."""
    from ds3d.util.threads import intra_op_threads

    with intra_op_threads(1):
        yield


@pytest.fixture(scope="session")
def lifter():
    """The bundled default lifter (models/posedb, Human3.6M S1-S9): what users get."""
    from ds3d.lifter import Lifter

    if not (MODELS_DIR / "posedb" / "poses.npy").is_file():
        pytest.fail("the bundled pose database models/posedb is missing")
    return Lifter.load()


@pytest.fixture(scope="session")
def small_model(data_dir, tmp_path_factory):
    """A --small 2D model (seed 3), trained here on real LSP data in seconds."""
    from ds3d.cli import main as cli

    out = tmp_path_factory.mktemp("image2d")
    assert cli(["train-2d", "--small", "--no-eval", "--out", str(out), "--seed", "3"]) == 0
    return out


@pytest.fixture(scope="session")
def model_dir(data_dir, tmp_path_factory):
    """A --small 2D model beside a link to the bundled pose database. Its person score is the
    bundled model's, a stand-in that lets it search (fitting one takes minutes)."""
    from ds3d.cli import main as cli
    from ds3d.people.score import PersonScore

    out = tmp_path_factory.mktemp("models")
    assert cli(["train-2d", "--small", "--no-eval", "--out", str(out / "image2d")]) == 0
    bundled = PersonScore.load(MODELS_DIR / "image2d")
    assert bundled is not None, "models/image2d/person_score.json"
    bundled.save(out / "image2d")
    (out / "posedb").symlink_to(MODELS_DIR / "posedb")
    return out
