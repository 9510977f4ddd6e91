"""What a test needs that a machine may lack: a dataset, a tool (nginx, jemalloc, chromium, git)
or an optional package (Ray, playwright, ...). Without it, a test is skipped, saying what is
missing and how to get it; under CI (the environment variable CI set to true, as CI services
set it) it fails instead: .ci/run installs everything, so a missing thing there is a broken
setup, and a skip would let the run pass with the test unrun.

Skips for what is not missing stay skips everywhere: no CUDA device, an advisory source that
cannot be reached."""

from __future__ import annotations

import importlib
import os
from types import ModuleType
from typing import NoReturn

import pytest


def under_ci() -> bool:
    """Whether this run is CI's: $CI is true (or 1)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1")


def missing(reason: str, module_level: bool = False) -> NoReturn:
    """Skip the test (or, with module_level, the module) for want of `reason`; under CI, fail
    it. Call it where the test finds the thing missing."""
    if under_ci():
        pytest.fail(f"missing under CI (CI=true): {reason}", pytrace=False)
    pytest.skip(reason, allow_module_level=module_level)


def import_or_missing(name: str, reason: str) -> ModuleType:
    """The module `name` imported, else missing(reason) at module level (pytest.importorskip,
    failing under CI)."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        missing(f"{reason} ({exc})", module_level=True)
