"""Where images come from: files, folders, globs, videos, a webcam and URLs, read one frame at a
time so that a folder of 100,000 images or an hour of video costs the memory of one batch.

    frames(["photo.jpg", "shots/", "clips/*.mp4", "0", "https://..."], stride=2)

yields a Frame per image or video frame, in order. A source that cannot be read (missing, not an
image, corrupt, an unreachable URL) yields one Frame with `error` set instead of stopping the
run. A file's kind is found by its first bytes, not its name: a folder contributes every image
below it, whatever its extension.
"""

from __future__ import annotations

import glob
import os
import tempfile
import urllib.request
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ds3d.errors import InvalidImage
from ds3d.io.images import DEFAULT_MAX_PIXELS, decode_image

# The most bytes read from a URL: a long video, far more than any photo.
MAX_URL_BYTES = 512 * 1024 * 1024
URL_TIMEOUT_S = 30.0
DEFAULT_FPS = 25.0  # a stream that does not say its frame rate


@dataclass
class Frame:
    """One image to estimate. source: the path, URL or "camera:N" it came from; index: the
    frame number in a video or camera stream (None for a still image); fps: the stream's frame
    rate (None for a still); image: (H, W, 3) uint8 RGB, None where `error` says why it could
    not be read."""

    source: str
    index: int | None = None
    fps: float | None = None
    image: np.ndarray | None = None
    error: str | None = None

    @property
    def name(self) -> str:
        """A short name for outputs: the file's stem, with the frame number for a video."""
        stem = Path(self.source.rstrip("/").split("?")[0]).stem or "image"
        return stem if self.index is None else f"{stem}_{self.index:06d}"


@dataclass(frozen=True)
class Source:
    """A source resolved to one readable thing: kind "image" or "video" (a file), "url",
    "camera" (its index in `location`), or "error" (`location` names it, `error` says why)."""

    kind: str
    location: str
    error: str | None = None


def sniff(head: bytes) -> str | None:
    """The kind of a file from its first 16 bytes: "image", "video", or None."""
    if head.startswith((b"\xff\xd8\xff", b"\x89PNG", b"GIF8", b"BM", b"II*\x00", b"MM\x00*")):
        return "image"
    if head[:4] == b"RIFF":
        return {b"WEBP": "image", b"AVI ": "video"}.get(head[8:12])
    if head[4:8] == b"ftyp":  # ISO media: MP4, MOV, 3GP; HEIF/AVIF stills share the box
        return "image" if head[8:12] in (b"avif", b"heic", b"heix", b"mif1") else "video"
    if head.startswith((b"\x1a\x45\xdf\xa3", b"\x00\x00\x01\xba", b"\x00\x00\x01\xb3")):
        return "video"  # Matroska / WebM, MPEG program stream, MPEG-1/2 video
    return None


def _file_kind(path: Path) -> str | None:
    try:
        with open(path, "rb") as f:
            return sniff(f.read(16))
    except OSError:
        return None


def resolve(sources: Iterable[str | os.PathLike]) -> Iterator[Source]:
    """Each command-line source as the readable things it names: a webcam index ("0"), an
    http(s) URL, a folder (every image below it, found by content: a folder's files in name
    order, then its subfolders'), a glob, or a file."""
    for given in sources:
        text = str(given)
        path = Path(text)
        if text.startswith(("http://", "https://")):
            yield Source("url", text)
        elif text.isdigit() and not path.exists():
            yield Source("camera", text)
        elif path.is_dir():
            for dirpath, dirnames, filenames in os.walk(path, followlinks=True):
                dirnames.sort()
                for name in sorted(filenames):
                    file = Path(dirpath) / name
                    if _file_kind(file) == "image":
                        yield Source("image", str(file))
        elif not path.exists() and glob.has_magic(text):
            matches = sorted(glob.glob(text, recursive=True))
            if not matches:
                yield Source("error", text, "the pattern matches no file")
            yield from resolve(matches)
        elif not path.exists():
            yield Source("error", text, "no such file or folder")
        else:
            kind = _file_kind(path)
            yield Source(kind, text) if kind else Source("error", text, "not an image or video")


def frames(
    sources: Iterable[str | os.PathLike], stride: int = 1, max_pixels: int = DEFAULT_MAX_PIXELS
) -> Iterator[Frame]:
    """Every image and every `stride`-th video or camera frame of `sources`, in order (see the
    module's docstring); still images decoded by ds3d.io.images (EXIF orientation applied)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    for source in resolve(sources):
        if source.kind == "error":
            yield Frame(source.location, error=source.error)
        elif source.kind == "image":
            yield _still(source.location, Path(source.location).read_bytes, max_pixels)
        elif source.kind == "video":
            yield from video_frames(source.location, stride)
        elif source.kind == "camera":
            yield from video_frames(int(source.location), stride)
        else:
            yield from _url_frames(source.location, stride, max_pixels)


def _still(location: str, read, max_pixels: int) -> Frame:
    try:
        return Frame(location, image=decode_image(read(), max_pixels))
    except (InvalidImage, OSError) as err:
        return Frame(location, error=str(err))


def video_frames(video: str | int, stride: int = 1) -> Iterator[Frame]:
    """Every `stride`-th frame of a video file (a path) or a camera (its index), RGB, read with
    OpenCV until the stream ends; one Frame with `error` if it cannot be opened."""
    name = f"camera:{video}" if isinstance(video, int) else str(video)
    capture = cv2.VideoCapture(video)
    try:
        if not capture.isOpened():
            yield Frame(name, error="cannot open the video or camera")
            return
        fps = capture.get(cv2.CAP_PROP_FPS) or None
        index = 0
        while True:
            if index % stride:
                ok = capture.grab()  # skipped: not decoded to pixels
            else:
                ok, bgr = capture.read()
                if ok:
                    yield Frame(name, index, fps, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
            if not ok:
                return
            index += 1
    finally:
        capture.release()


def _url_frames(url: str, stride: int, max_pixels: int) -> Iterator[Frame]:
    """An image or a video at an http(s) URL: downloaded (at most MAX_URL_BYTES), its kind found
    by content; a video is read from a temporary file, deleted after."""
    try:
        with urllib.request.urlopen(url, timeout=URL_TIMEOUT_S) as response:
            data = response.read(MAX_URL_BYTES + 1)
    except (OSError, ValueError) as err:
        yield Frame(url, error=f"cannot download: {err}")
        return
    if len(data) > MAX_URL_BYTES:
        yield Frame(url, error=f"more than {MAX_URL_BYTES} bytes")
        return
    if sniff(data[:16]) != "video":
        yield _still(url, lambda: data, max_pixels)
        return
    with tempfile.NamedTemporaryFile(suffix=".video") as file:
        file.write(data)
        file.flush()
        for frame in video_frames(file.name, stride):
            frame.source = url
            yield frame
