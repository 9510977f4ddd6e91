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

import numpy as np

from ds3d.errors import InvalidBox, InvalidImage
from ds3d.inputs import MIN_SCORE, ImageInput, image_input
from ds3d.io.prediction import Prediction
from ds3d.io.sources import DEFAULT_FPS, Frame, frames
from ds3d.people.tracking import Tracker
from ds3d.pipeline import Pipeline
from ds3d.runners.workers import PipelineWorkers

log = logging.getLogger("ds3d")


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


def _checked(
    stream: Iterator[Frame], on_skip: Callable[[Frame], None], **options
) -> Iterator[tuple[Frame, ImageInput]]:
    """The frames that decoded, each with its image checked with `options` (ds3d.inputs.
    image_input: bbox, focal_px, people, min_score); those that did not decode, or cannot hold
    the box (without one: that the search cannot take), handed to on_skip."""
    for frame in stream:
        item = None
        if frame.error is None:
            try:
                item = image_input(frame.image, **options)
            except (InvalidBox, InvalidImage) as err:
                frame.error = str(err)
        if item is None:
            on_skip(frame)
        else:
            yield frame, item


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
    or a ds3d.runners.workers.PipelineWorkers, its batches split among its processes).
    stride: every n-th frame of a video or camera; bbox: one person box (x0, y0, x1, y1) px for
    every image (default: people are searched for); people, min_score, iterations, focal_px:
    as Pipeline.estimate. The people of a video's or a camera's frames are tracked, each with
    its track_id, and with `smooth` their 3D joints smoothed along the track (ds3d.people.tracking).
    Unreadable sources, images that cannot hold bbox and, without one,
    images too elongated to search go to `on_skip` (default: a logged warning)."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    pipeline = pipeline or _default_pipeline(device)
    options = {"bbox": bbox, "focal_px": focal_px, "people": people, "min_score": min_score}
    checked = _checked(_stream(sources, stride), on_skip, **options)
    trackers: dict[str, Tracker] = {}
    while batch := list(itertools.islice(checked, batch_size)):
        result = pipeline.run([item for _, item in batch], iterations)
        for i, (frame, _) in enumerate(batch):
            found = result.people(i)
            if frame.index is not None:
                tracker = trackers.setdefault(frame.source, Tracker(smooth))
                found = tracker.update(found, stride / (frame.fps or DEFAULT_FPS))
            yield Prediction(frame, found)
