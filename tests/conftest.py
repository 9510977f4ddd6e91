"""Shared fixtures. Tests that need the datasets skip when $DS3D_DATA is absent; CI has them."""

from __future__ import annotations

import pytest
import torch

from ds3d.paths import MODELS_DIR, data_root


def pytest_configure(config):
    torch.set_num_threads(2)


@pytest.fixture(scope="session")
def data_dir():
    root = data_root()
    if not root.is_dir():
        pytest.skip(f"datasets not found at {root} (set DS3D_DATA)")
    return root


@pytest.fixture(scope="session")
def lifter():
    """The bundled default lifter (models/posedb, Human3.6M S1-S9): what users get."""
    from ds3d.lifter import Lifter

    if not (MODELS_DIR / "posedb" / "poses.npy").is_file():
        pytest.fail("the bundled pose database models/posedb is missing")
    return Lifter.load()
