"""The cascade's layers (ds3d.training.forests), grown on real LSP data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ds3d.image2d.params import EstimatorParams
from ds3d.training.config import TrainConfig
from ds3d.training.forests import grow_cascade
from ds3d.training.images import training_annotations
from ds3d.training.psm import fit_psm


@pytest.mark.usefixtures("data_dir")
def test_a_resumed_cascade_ends_where_an_uninterrupted_one_does(tmp_path):
    cfg = TrainConfig(
        max_images=24, trees=(2, 2), images_per_tree=8, pool_size=64, max_depth=6, psm_iterations=5
    )
    ann = training_annotations(cfg)[0]
    params = EstimatorParams()
    mixtures = fit_psm(ann, cfg, params)
    items = [[(i, False) for i in range(12)], [(i, bool(i % 2)) for i in range(12, 24)]]
    checkpoint = tmp_path / "checkpoint"
    rng = np.random.default_rng(0)
    whole, _ = grow_cascade(ann, items, cfg, params, mixtures, rng, checkpoint)
    # A run stopped after layer 1 leaves only that layer; the resumed run reads it and the
    # random state after it, whatever state its own generator starts in.
    (checkpoint / "forest2.pt").unlink()
    rng = np.random.default_rng(99)
    resumed, _ = grow_cascade(ann, items, cfg, params, mixtures, rng, checkpoint)
    for a, b in zip(whole, resumed, strict=True):
        for name, value in a.to_dict().items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, b.to_dict()[name]), name
            else:
                assert value == b.to_dict()[name], name
