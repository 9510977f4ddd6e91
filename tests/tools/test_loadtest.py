"""The load-test tool's inputs: image files from a folder or a glob, and 2D poses from a file in
`ds3d lift`'s input format. The tool against a real service is in test_app.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tools.loadtest import image_files, image_payloads, read_poses


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


def test_poses_come_from_a_lift_input_file(tmp_path):
    path = tmp_path / "poses.json"
    joints = np.arange(2 * 14 * 2, dtype=np.float32).reshape(2, 14, 2)
    path.write_text(json.dumps({"joints_2d": joints.tolist()}))
    xy, visible = read_poses(path)
    np.testing.assert_array_equal(xy, joints)
    assert visible.shape == (2, 14) and visible.all()
    path.write_text(json.dumps({"joints_2d": joints[:, :3].tolist()}))
    with pytest.raises(SystemExit, match="shape"):
        read_poses(path)
