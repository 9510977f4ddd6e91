"""Accuracy regression of the committed 2D model on the first 100 LSP test images (the forest
cascade, the joint network and the PSM; "unary_argmax" is the per-joint argmax of their summed
unaries).

The floors are the PCK@0.2 measured with `ds3d eval lsp --limit 100` when the model was
committed (docs/RESULTS.md, 2D stage) minus a margin of 3 points, which absorbs float differences
across machines, not a real regression.
"""

import pytest
import torch

from ds3d.data.lsp import load_lsp
from ds3d.evaluation.lsp import evaluate_2d
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.util.paths import MODELS_DIR, data_root

MEASURED = {"psm": 0.7971, "unary_argmax": 0.7871}  # PCK@0.2, first 100 LSP test images
MARGIN = 0.03


@pytest.mark.slow
@pytest.mark.skipif(
    not (data_root() / "lsp" / "joints.mat").is_file(), reason="LSP data not available"
)
def test_pck_on_100_lsp_test_images_does_not_regress():
    torch.set_num_threads(1)
    test = load_lsp(split="test").subset(range(100))
    result = evaluate_2d(PoseEstimator2D.load(MODELS_DIR / "image2d"), test)
    for name, floor in MEASURED.items():
        assert result[name]["pck@0.2"] >= floor - MARGIN, (name, result[name])
