"""Where ds3d finds the datasets and the bundled models."""

from __future__ import annotations

import os
from pathlib import Path

from ds3d.errors import DataFormatError

MODEL_DIR_ENV = "DS3D_MODEL_DIR"
PACKAGE_DIR = Path(__file__).resolve().parent.parent  # ds3d/, above util/
PROJECT_ROOT = PACKAGE_DIR.parent
# The bundled models: models/ at the top of a source checkout; in an installed wheel, the
# package data ds3d/models (pyproject.toml maps the package ds3d.models onto models/).
CHECKOUT_MODELS_DIR = PROJECT_ROOT / "models"
PACKAGE_MODELS_DIR = PACKAGE_DIR / "models"


def in_checkout() -> bool:
    """Whether ds3d runs from a source checkout (as an editable install too), not a wheel."""
    return (PROJECT_ROOT / "pyproject.toml").is_file()


def models_dir() -> Path:
    """The models: $DS3D_MODEL_DIR if set; else, running from a source checkout, its models/;
    else the package data of the installed ds3d. MODELS_DIR holds it as of import."""
    if os.environ.get(MODEL_DIR_ENV):
        return Path(os.environ[MODEL_DIR_ENV]).expanduser().absolute()
    return CHECKOUT_MODELS_DIR if in_checkout() else PACKAGE_MODELS_DIR


MODELS_DIR = models_dir()


def where_models_are() -> str:
    """Where ds3d looks for its models, in order, as an error message says it."""
    env = os.environ.get(MODEL_DIR_ENV)
    checkout = CHECKOUT_MODELS_DIR if in_checkout() else "none: ds3d is installed"
    return (
        f"ds3d takes its models from ${MODEL_DIR_ENV} ({f'= {env}' if env else 'unset'}), "
        f"else from the models/ folder of a source checkout ({checkout}), else from the package "
        f"data of the installed ds3d ({PACKAGE_MODELS_DIR}): set {MODEL_DIR_ENV} to a folder "
        "holding image2d/ and posedb/, or install ds3d from a wheel that carries its models"
    )


def require_models(path: str | Path) -> Path:
    """`path`, a model folder or file, when it exists. Else DataFormatError; for a path in
    MODELS_DIR (every loader's default), one that says where ds3d looks for its models."""
    path = Path(path)
    if path.exists():
        return path
    if path.resolve().is_relative_to(MODELS_DIR.resolve()):
        raise DataFormatError(f"no models at {path}. {where_models_are()}")
    raise DataFormatError(f"no such model folder or file: {path}")


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
