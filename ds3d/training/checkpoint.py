"""Training progress on disk (`ds3d train-2d --resume`, `ds3d train-jointnet --resume`)."""

from __future__ import annotations

from pathlib import Path

import torch


def save_checkpoint(state: dict, path: Path) -> None:
    """torch.save(state, path), written whole or not at all: an interrupted write leaves the
    previous checkpoint in place, never a truncated one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    torch.save(state, partial)
    partial.replace(path)
