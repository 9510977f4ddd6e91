"""ds3d.runners.workers: a batch split among worker processes answers as one Pipeline does."""

from __future__ import annotations

import signal

import numpy as np
import pytest
import torch

from ds3d.boxes import person_boxes
from ds3d.data.lsp import load_lsp
from ds3d.errors import InvalidBox
from ds3d.io.images import read_image
from ds3d.pipeline import Pipeline
from ds3d.runners.workers import PipelineWorkers


@pytest.fixture(scope="module")
def images(data_dir):
    return [read_image(p) for p in load_lsp(split="test").image_paths[:5]]


@pytest.fixture(scope="module")
def pipeline():
    return Pipeline.load()


@pytest.fixture(scope="module")
def workers():
    with PipelineWorkers(2) as pool:
        yield pool


def test_workers_answer_as_one_pipeline(workers, images, pipeline):
    """Per-image options go with their images: boxes, intrinsics, people and min_score."""
    boxes = [None, *person_boxes(load_lsp(split="test").joints[1:5])]
    focal = [1000.0 + 100 * i for i in range(5)]
    options = {
        "bboxes": boxes,
        "intrinsics": np.stack([[[f, 0, 90], [0, f, 120], [0, 0, 1]] for f in focal]),
        "people": ["all", "best", "best", "all", "best"],
        "min_score": [0.2, 0.5, 0.5, 0.9, 0.5],
    }
    pooled = workers.estimate(images, **options)
    alone = pipeline.estimate(images, **options)
    torch.testing.assert_close(pooled.image_index, alone.image_index)
    torch.testing.assert_close(pooled.joints_2d, alone.joints_2d)
    torch.testing.assert_close(pooled.score, alone.score)
    # the 3D fit's rounding depends on how many people are lifted together
    torch.testing.assert_close(pooled.joints_3d, alone.joints_3d, atol=0.5, rtol=0)  # mm
    assert pooled.joint_set == alone.joint_set
    assert set(pooled.timings_ms) == set(alone.timings_ms)


def test_a_workers_error_reaches_the_caller(workers, images):
    with pytest.raises(InvalidBox):
        workers.estimate(images[:3], bboxes=[None, (10, 10, 5, 40), None])


def test_fewer_images_than_workers(workers, images):
    one = workers.estimate(images[:1])
    assert one.image_index.tolist() == [0]


def test_no_images_no_people(workers, pipeline):
    assert len(workers.estimate([]).image_index) == 0 == len(pipeline.estimate([]).image_index)


def test_ctrl_c_is_left_to_the_parent(workers):
    """Ctrl+C reaches the whole process group: the workers ignore it, so the parent (the
    service, a script) stops them in order rather than each dying with a traceback."""
    for _ in range(workers.workers):
        assert workers._pool.submit(signal.getsignal, signal.SIGINT).result() == signal.SIG_IGN
