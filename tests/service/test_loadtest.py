"""The load-test tool's inputs: image files from a folder or a glob, and its own reading of the
LSP annotations, which must give what ds3d.data.lsp gives. The tool against a real service is in
test_app.py."""

from __future__ import annotations

import numpy as np
import pytest

from service.loadtest import image_files, image_payloads, lsp_poses


def test_images_come_from_a_folder_or_a_glob(tmp_path):
    for name in ("b.jpg", "a.PNG", "notes.txt", "sub/c.jpg"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in image_files(tmp_path)] == ["a.PNG", "b.jpg"]  # not into sub/
    assert [p.name for p in image_files(str(tmp_path / "*.jpg"))] == ["b.jpg"]
    assert [p.name for p in image_files(str(tmp_path / "**" / "*.jpg"))] == ["b.jpg", "c.jpg"]
    assert image_payloads(str(tmp_path), 1) == [("a.PNG", b"x")]
    with pytest.raises(SystemExit):
        image_payloads(str(tmp_path / "*.bmp"), 1)


def test_lsp_poses_match_the_library_reader(data_dir):
    from ds3d.data.lsp import load_lsp

    xy, visible = lsp_poses(data_dir / "lsp")
    lsp = load_lsp(data_dir / "lsp")
    np.testing.assert_array_equal(xy, lsp.joints)
    np.testing.assert_array_equal(visible, lsp.visible)
