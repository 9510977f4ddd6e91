"""Accuracy of the committed 2D model on LSP test (im1001-im2000, `ds3d eval lsp`: the forest
cascade, the joint network and the PSM; "unary_argmax" is the per-joint argmax of their summed
unaries), against the figures the model records for itself: `ds3d eval lsp --write-manifest`
writes them into models/image2d/manifest.json (metrics.lsp_test), so that a model retrained, or
an inference changed on purpose, brings its own by running that command again.
"""

import json
from dataclasses import replace

import numpy as np
import pytest

from ds3d.boxes import iou, person_boxes
from ds3d.data.lsp import load_lsp
from ds3d.evaluation.lsp import evaluate_2d
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.io.images import read_image
from ds3d.pipeline import Pipeline
from ds3d.util.paths import MODELS_DIR

# How far another machine may measure from the recorded PCK@0.2. On one machine the figures are
# the same on 1 and 2 threads; across machines the joint network computes differently: bfloat16
# on a CPU with AVX-512 BF16, int8 on other x86 CPUs (ds3d.image2d.quantized), float32 elsewhere.
# On the full test set the three gave PSM 79.09 (int8), 78.83 (float32) and 78.90 % (bfloat16),
# the unaries' argmax 77.56, 77.64 and 77.72 %: within 0.3 points of each other, and within 0.35
# of the manifest's figures. Half a point holds them and catches a regression of a point (14
# joints in every hundred images).
PCK_TOLERANCE = 0.005
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.slow
def test_pck_on_lsp_test_is_as_the_model_records(data_dir):
    recorded = json.loads((MODELS_DIR / "image2d" / "manifest.json").read_text())["metrics"]
    recorded = recorded["lsp_test"]
    measured = evaluate_2d(PoseEstimator2D.load(MODELS_DIR / "image2d"), load_lsp(split="test"))
    assert measured["n_images"] == recorded["n_images"] == 1000
    for name in ("psm", "unary_argmax"):
        pck, expected = measured[name]["pck@0.2"], recorded[name]["pck@0.2"]
        assert abs(pck - expected) <= PCK_TOLERANCE, (
            f"{name}: PCK@0.2 {pck:.4f} against {expected:.4f} in the model's manifest: if the "
            "change is meant, record it with `ds3d eval lsp --write-manifest`"
        )


@pytest.mark.slow
def test_people_the_photo_cuts_off_reach_past_its_edge(data_dir):
    """LSP test people standing in full view, the photo cut a quarter of their height above
    their lowest joint (their feet gone, often their knees), searched for without a box: the
    bundled pipeline, its search and crops reaching past the edge (SearchParams and
    InferenceParams beyond_edge), poses many of them with joints past the bottom edge, where
    one held to the image never does, and finds them as often (its box against what the photo
    shows of their true one, at IoU >= 0.5: the people protocol's match)."""
    test = load_lsp(split="test").subset(range(120))
    reaching = Pipeline.load()
    assert reaching.config.search.beyond_edge > 0 and reaching.estimator.params.beyond_edge > 0
    held_in = Pipeline.load()
    held_in.config = replace(held_in.config, search=replace(held_in.config.search, beyond_edge=0))
    held_in.estimator.params = held_in.estimator.params.with_inference(beyond_edge=0.0)
    images, truth = [], []
    for i in range(len(test)):
        joints = test.joints[i]
        top, bottom = joints[:, 1].min(), joints[:, 1].max()
        upright = joints[[0, 5], 1].min() > joints[[2, 3], 1].max()  # ankles below the hips
        if test.located[i].all() and upright and len(images) < 24:
            cut = int(bottom - 0.25 * (bottom - top))
            images.append(np.ascontiguousarray(read_image(test.image_paths[i])[:cut]))
            truth.append(joints)
    assert len(images) == 24
    heights = np.array([image.shape[0] for image in images])

    def shown(joints: np.ndarray, k: int) -> np.ndarray:  # (1, 4) the box within image k
        h, w = images[k].shape[:2]
        return np.clip(person_boxes(joints[None]), 0, [w, h, w, h])

    past, found = {}, {}
    for name, pipeline in (("reaching", reaching), ("held_in", held_in)):
        poses = pipeline.estimate(images).joints_2d_initial.numpy()
        past[name] = (poses[..., 1].max(1) >= heights).mean()
        overlap = [iou(shown(poses[k], k), shown(truth[k], k))[0, 0] for k in range(len(images))]
        found[name] = (np.array(overlap) >= 0.5).sum()
    assert past["reaching"] >= 0.4 and past["held_in"] == 0, past
    assert found["reaching"] >= found["held_in"], found
