"""The load tools' inputs, from LSP test."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ds3d.data.lsp import load_lsp


@pytest.fixture
def load_inputs(data_dir, tmp_path) -> tuple[Path, Path]:
    """(poses file, images folder) for the load tools (soak, crash test): 64 LSP test poses in
    `ds3d lift`'s input format and 8 LSP test images."""
    lsp = load_lsp(split="test")
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps({"joints_2d": lsp.joints[:64].tolist()}))
    images = tmp_path / "images"
    images.mkdir()
    for path in lsp.image_paths[:8]:
        (images / path.name).write_bytes(path.read_bytes())
    return poses, images
