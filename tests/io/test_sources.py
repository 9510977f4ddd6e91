"""Sources of `ds3d predict` (ds3d.io.sources): folders by content, globs, videos made here with
OpenCV, a URL served by a local HTTP server; what cannot be read is reported, not fatal."""

from __future__ import annotations

import functools
import http.server
import threading

import cv2
import numpy as np
import pytest
from PIL import Image

from ds3d.io.sources import frames, resolve, sniff


def _jpeg(path, size=(40, 30), value=128):
    Image.fromarray(np.full((size[1], size[0], 3), value, np.uint8)).save(path, format="JPEG")


def _video(path, count=7, size=(64, 48), fps=10.0):
    """An MP4 of `count` frames, frame k filled with grey level 20 * k."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    assert writer.isOpened()
    for k in range(count):
        writer.write(np.full((size[1], size[0], 3), 20 * k, np.uint8))
    writer.release()


def test_a_folder_gives_every_image_below_it_by_content_in_name_order(tmp_path):
    (tmp_path / "b").mkdir()
    _jpeg(tmp_path / "z.jpg")
    _jpeg(tmp_path / "b" / "no_suffix")
    Image.fromarray(np.zeros((5, 6, 3), np.uint8)).save(tmp_path / "b" / "a.png")
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "fake.jpg").write_text("not an image either")
    found = list(frames([tmp_path]))
    assert [f.source for f in found] == [
        str(tmp_path / "z.jpg"),  # a folder's own files first, then its subfolders'
        str(tmp_path / "b" / "a.png"),
        str(tmp_path / "b" / "no_suffix"),
    ]
    assert all(f.error is None and f.image.dtype == np.uint8 for f in found)
    assert found[1].image.shape == (5, 6, 3) and found[2].image.shape == (30, 40, 3)


def test_bad_sources_are_frames_with_an_error_and_the_rest_go_on(tmp_path):
    _jpeg(tmp_path / "good.jpg")
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "good.jpg").read_bytes()[:200])
    (tmp_path / "text.jpg").write_text("hello")
    given = [tmp_path / "missing.jpg", tmp_path / "text.jpg", tmp_path / "cut.jpg"]
    found = list(frames([*given, tmp_path / "good.jpg", str(tmp_path / "*.none")]))
    errors = [f.error for f in found]
    assert errors[0] == "no such file or folder" and errors[1] == "not an image or video"
    assert "truncated" in errors[2] and errors[3] is None
    assert errors[4] == "the pattern matches no file"


def test_a_glob_expands_recursively(tmp_path):
    (tmp_path / "x" / "y").mkdir(parents=True)
    _jpeg(tmp_path / "x" / "one.jpg")
    _jpeg(tmp_path / "x" / "y" / "two.jpg")
    found = list(frames([str(tmp_path / "**" / "*.jpg")]))
    assert sorted(f.source for f in found) == [
        str(tmp_path / "x" / "one.jpg"),
        str(tmp_path / "x" / "y" / "two.jpg"),
    ]


def test_a_video_gives_every_stride_th_frame_with_its_index_and_rate(tmp_path):
    path = tmp_path / "clip.mp4"
    _video(path)
    (source,) = resolve([path])
    assert source.kind == "video"
    every = list(frames([path]))
    assert [f.index for f in every] == list(range(7)) and every[0].fps == pytest.approx(10.0)
    third = list(frames([path], stride=3))
    assert [f.index for f in third] == [0, 3, 6] and third[1].name == "clip_000003"
    # frame k is grey 20 k (lossy codec: within a few levels)
    assert [round(float(f.image.mean()) / 20) for f in third] == [0, 3, 6]


def test_a_camera_index_that_does_not_open_is_reported():
    (frame,) = frames(["917"])
    assert frame.source == "camera:917" and frame.error == "cannot open the video or camera"


def test_urls_of_an_image_and_a_video_from_a_local_server(tmp_path):
    _jpeg(tmp_path / "photo", value=200)  # no suffix: found by content
    _video(tmp_path / "clip.mp4", count=4)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        found = list(frames([f"{base}/photo", f"{base}/clip.mp4", f"{base}/missing.jpg"]))
    finally:
        server.shutdown()
    assert found[0].error is None and found[0].image.shape == (30, 40, 3)
    assert abs(float(found[0].image.mean()) - 200) < 3
    assert [f.index for f in found[1:5]] == [0, 1, 2, 3]
    assert all(f.source == f"{base}/clip.mp4" for f in found[1:5])
    assert found[5].error.startswith("cannot download") and "404" in found[5].error


def test_sniff_knows_the_common_containers():
    assert sniff(b"\xff\xd8\xff\xe0" + bytes(12)) == "image"
    assert sniff(b"RIFF\0\0\0\0WEBPVP8 ") == "image"
    assert sniff(b"RIFF\0\0\0\0AVI LIST") == "video"
    assert sniff(b"\0\0\0\x18ftypmp42\0\0\0\0") == "video"
    assert sniff(b"\0\0\0\x18ftypheic\0\0\0\0") == "image"
    assert sniff(b"\x1a\x45\xdf\xa3" + bytes(12)) == "video"
    assert sniff(b"hello world, no.") is None
