"""Where ds3d finds the datasets and the bundled models."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
MODELS_DIR = PROJECT_ROOT / "models"


def data_root() -> Path:
    """The read-only datasets: $DS3D_DATA, else ../shared/data beside the project."""
    return Path(os.environ.get("DS3D_DATA", PROJECT_ROOT.parent / "shared" / "data"))


def project_relative(path: Path) -> str:
    """A path as reports record it: relative to the project if inside it (so that a manifest
    reads the same on every checkout), else as given."""
    resolved = Path(path).resolve()
    if resolved.is_relative_to(PROJECT_ROOT):
        return str(resolved.relative_to(PROJECT_ROOT))
    return str(path)
