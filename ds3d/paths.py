"""Where ds3d finds the datasets and the bundled models."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
MODELS_DIR = PROJECT_ROOT / "models"


def data_root() -> Path:
    """The read-only datasets: $DS3D_DATA, else ../shared/data beside the project."""
    return Path(os.environ.get("DS3D_DATA", PROJECT_ROOT.parent / "shared" / "data"))
