"""Predictions over any source, streamed in batches: what `ds3d predict` and `ds3d.predict` run.

    for result in ds3d.predict("holiday/", batch_size=16):
        print(result.source, result.people.joints_3d.shape)
        picture = result.plot()  # (H, W, 3) uint8 RGB

Sources are those of ds3d.io.sources (files, folders, globs, videos, webcam indices, URLs) and
(H, W, 3) uint8 RGB arrays; images are read as batches are filled, so memory stays that of one
batch. A source that cannot be read is skipped and handed to `on_skip`.
"""

from __future__ import annotations

import functools
import itertools
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from ds3d.boxes import checked_box
from ds3d.errors import InvalidBox, InvalidImage
from ds3d.image2d.search import SearchParams, check_searchable
from ds3d.io.sources import DEFAULT_FPS, Frame, frames
from ds3d.pipeline import MIN_SCORE, Pipeline
from ds3d.result import Person
from ds3d.tracking import Tracker
from ds3d.viz.overlay import plot
from ds3d.workers import PipelineWorkers

log = logging.getLogger("ds3d")


@dataclass
class Prediction:
    """One image's (or video frame's) answer: the frame it came from (source, index, fps,
    image) and its people, best first (one with people="best")."""

    frame: Frame
    people: list[Person]

    @property
    def source(self) -> str:
        return self.frame.source

    @property
    def image(self) -> np.ndarray:
        image = self.frame.image
        assert image is not None, "a prediction is made of a frame that was read"
        return image

    def to_dict(self) -> dict:
        """JSON-ready: source, frame index, image size and every person (Person.to_json)."""
        height, width = self.image.shape[:2]
        return {
            "source": self.source,
            "frame": self.frame.index,
            "width": width,
            "height": height,
            "people": [person.to_json() for person in self.people],
        }

    def plot(self, with_3d: bool = True) -> np.ndarray:
        """The image with every person's 2D skeleton and, with_3d, their 3D skeletons on a
        panel beside it: (H, W [+ 3H/4], 3) uint8 RGB (ds3d.viz.overlay)."""

        def stacked(name: str) -> np.ndarray:  # (N, ...) of every person's field
            return np.array([getattr(person, name) for person in self.people])

        joints_3d = stacked("joints_3d") if with_3d else None
        return plot(self.image, stacked("joints_2d"), joints_3d, stacked("confidence"))


def _stream(sources, stride: int) -> Iterator[Frame]:
    """Frames of paths and URLs (ds3d.io.sources.frames) and of arrays, in the given order."""
    if isinstance(sources, str | os.PathLike | np.ndarray):
        sources = [sources]
    runs = itertools.groupby(enumerate(sources), key=lambda item: isinstance(item[1], np.ndarray))
    for is_array, items in runs:
        if is_array:
            yield from (Frame(f"array:{i}", image=image) for i, image in items)
        else:
            yield from frames([source for _, source in items], stride)


def _readable(stream: Iterator[Frame], bbox, search: SearchParams, on_skip) -> Iterator[Frame]:
    """The frames that decoded and that hold `bbox` (without one: that the search can take);
    the others handed to on_skip."""
    for frame in stream:
        if frame.error is None:
            assert frame.image is not None, "a frame without an error was read"
            height, width = frame.image.shape[:2]
            try:
                if bbox is None:
                    check_searchable(height, width, search)
                else:
                    checked_box(bbox, width, height)
            except (InvalidBox, InvalidImage) as err:
                frame.error = str(err)
        if frame.error is None:
            yield frame
        else:
            on_skip(frame)


def _log_skip(frame: Frame) -> None:
    log.warning("skipped %s: %s", frame.source, frame.error)


@functools.cache
def _default_pipeline(device: str) -> Pipeline:
    return Pipeline.load(device=device)


def predict(
    sources: Iterable | str | os.PathLike | np.ndarray,
    pipeline: Pipeline | PipelineWorkers | None = None,
    *,
    batch_size: int = 16,
    stride: int = 1,
    bbox=None,
    people: str = "best",
    min_score: float = MIN_SCORE,
    iterations: int | None = None,
    focal_px: float | None = None,
    smooth: bool = True,
    device: str = "cpu",
    on_skip: Callable[[Frame], None] = _log_skip,
) -> Iterator[Prediction]:
    """A Prediction per readable image or frame of `sources`, in order, estimated `batch_size`
    at a time by `pipeline` (default: the bundled models, loaded once per process on `device`;
    or a ds3d.workers.PipelineWorkers, its batches split among its processes).
    stride: every n-th frame of a video or camera; bbox: one person box (x0, y0, x1, y1) px for
    every image (default: people are searched for); people, min_score, iterations, focal_px:
    as Pipeline.estimate. The people of a video's or a camera's frames are tracked, each with
    its track_id, and with `smooth` their 3D joints smoothed along the track (ds3d.tracking).
    Unreadable sources, images that cannot hold bbox and, without one,
    images too elongated to search go to `on_skip` (default: a logged warning)."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    pipeline = pipeline or _default_pipeline(device)
    readable = _readable(_stream(sources, stride), bbox, pipeline.config.search, on_skip)
    trackers: dict[str, Tracker] = {}
    while batch := list(itertools.islice(readable, batch_size)):
        result = pipeline.estimate(
            [f.image for f in batch],
            bboxes=None if bbox is None else [bbox] * len(batch),
            iterations=iterations,
            people=people,
            min_score=min_score,
            focal_px=focal_px,
        )
        for i, frame in enumerate(batch):
            found = result.people(i)
            if frame.index is not None:
                tracker = trackers.setdefault(frame.source, Tracker(smooth))
                found = tracker.update(found, stride / (frame.fps or DEFAULT_FPS))
            yield Prediction(frame, found)
