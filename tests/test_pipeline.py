"""ds3d.Pipeline end to end on real LSP images, with a small 2D model trained here (seconds) and
the bundled pose database; plus the bundled default model as a user gets it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ds3d.boxes import person_boxes
from ds3d.data.lsp import load_lsp
from ds3d.errors import InvalidBox
from ds3d.fit.energy import limb_lengths
from ds3d.image2d.result import LOG_EPS, Estimate2D
from ds3d.io.images import read_image
from ds3d.iterative import neighbour_scores
from ds3d.lifter import LifterConfig
from ds3d.pipeline import Pipeline, PipelineConfig
from ds3d.refine import cells_to_image, image_to_cells
from ds3d.skeleton import L_HIP, NUM_JOINTS, R_HIP, SET_NAMES
from ds3d.util.paths import MODELS_DIR


@pytest.fixture(scope="module")
def pipeline(model_dir):
    return Pipeline.load(model_dir)


@pytest.fixture(scope="module")
def images(data_dir):
    paths = load_lsp(split="test").image_paths[:4]
    return [read_image(p) for p in paths]


def test_real_image_gives_finite_poses_of_the_right_shapes(pipeline, images):
    pipeline.config = PipelineConfig(iterations=2)  # the paper's, one more than the default
    try:
        res = pipeline.estimate(images[:1])
    finally:
        pipeline.config = PipelineConfig()
    assert res.joints_2d.shape == res.joints_2d_initial.shape == (1, NUM_JOINTS, 2)
    assert res.joints_2d_iterations.shape == (1, 2, NUM_JOINTS, 2)
    assert res.joints_3d.shape == (1, NUM_JOINTS, 3) and res.confidence.shape == (1, NUM_JOINTS)
    for t in (res.joints_2d, res.joints_3d, res.confidence, res.psm_energy):
        assert bool(torch.isfinite(t).all())
    assert bool(((res.confidence >= 0) & (res.confidence <= 1)).all())
    assert res.facing_camera.shape == (1,) and 0 <= float(res.facing_camera[0]) <= 1
    torch.testing.assert_close(
        (res.joints_3d[:, R_HIP] + res.joints_3d[:, L_HIP]) / 2,
        torch.zeros(1, 3),
        atol=1e-3,
        rtol=0,
    )
    # a person-sized skeleton, whatever the pose: the database's bones sum to 4.1-4.6 m
    bones = limb_lengths(res.joints_3d[0])
    assert 3500 < float(bones.sum()) < 5200 and float(bones.max()) < 700, bones
    h, w = images[0].shape[:2]
    assert bool(
        (res.joints_2d[..., 0].abs() < 2 * w).all() & (res.joints_2d[..., 1].abs() < 2 * h).all()
    )
    assert res.joint_set[0] in SET_NAMES and res.iterations == 2
    assert {
        "2d_traversal",
        "retrieval",
        "projection_fit",
        "refinement",
        "pose_fit",
        "total",
    } <= set(res.timings_ms)


def test_people_are_placed_in_front_of_the_camera_at_a_depth_its_focal_length_sets(
    pipeline, images
):
    """Without intrinsics a photo's people are placed by an assumed camera (flagged so) or the
    focal length given: twice the focal length, twice the depth, the same x and y (a weak-
    perspective fit is drawn at the scale it fitted whatever the camera)."""
    assumed = pipeline.estimate(images[:2])
    assert bool(assumed.focal_assumed.all()) and bool((assumed.root_position[:, 2] > 0).all())
    given = pipeline.estimate(images[:2], focal_px=600.0)
    twice = pipeline.estimate(images[:2], focal_px=1200.0)
    assert not bool(given.focal_assumed.any()) and given.focal_px.tolist() == [600.0, 600.0]
    torch.testing.assert_close(twice.root_position[:, 2], 2 * given.root_position[:, 2])
    torch.testing.assert_close(twice.root_position[:, :2], given.root_position[:, :2])
    person = given.person(0)
    np.testing.assert_allclose(person.joints_3d_camera, person.joints_3d + person.root_position)


def test_further_iterations_never_raise_the_psm_energy(pipeline, images):
    res = pipeline.estimate(images, iterations=3)
    energy = res.psm_energy
    assert energy.shape == (len(images), 3)
    assert bool((energy[:, 1:] <= energy[:, :-1]).all()), energy
    # the answer is the pose of the last (best) energy
    torch.testing.assert_close(res.joints_2d, res.joints_2d_iterations[:, -1])


def test_neighbour_weights_follow_eq_wt_and_eq_wtn(pipeline):
    gen = torch.Generator().manual_seed(0)
    b, s, k, h, w = 2, 5, 40, 20, 30
    unaries = torch.log(torch.rand(b, NUM_JOINTS, h, w, generator=gen) + LOG_EPS)
    # cell (u, v) is image pixel (2u + 1, 3v - 2)
    affine = torch.tensor([[2.0, 0.0, 1.0], [0.0, 3.0, -2.0]]).expand(b, 2, 3)
    est = dataclasses.replace(
        pipeline.estimator.estimate([np.zeros((60, 40, 3), np.uint8)] * b),
        unaries=unaries,
        map_to_image=affine,
    )
    cells = torch.stack(
        [
            torch.randint(0, w, (b, s, k, NUM_JOINTS), generator=gen),
            torch.randint(0, h, (b, s, k, NUM_JOINTS), generator=gen),
        ],
        -1,
    )
    points = cells_to_image(cells.float().view(b, -1, 2), affine).view(b, s, k, NUM_JOINTS, 2)
    torch.testing.assert_close(
        image_to_cells(points.view(b, -1, 2), affine).view(cells.shape), cells.float()
    )
    scores = neighbour_scores(est, points)
    joint = torch.arange(NUM_JOINTS)
    want = torch.stack(
        [unaries[i][joint, cells[i, ..., 1], cells[i, ..., 0]].sum(-1) for i in range(b)]
    )  # eq:wt at grid points: the sum of the unaries at the joints
    torch.testing.assert_close(scores, want, atol=1e-4, rtol=0)

    pipeline.lifter.configure(LifterConfig(neighbours=k, weighted_neighbours=16))
    try:
        candidates = torch.randn(b, s, k, NUM_JOINTS, 3, generator=gen)
        kept, weights, _ = pipeline.lifter.weight_neighbours(candidates, scores)
    finally:
        pipeline.lifter.configure(LifterConfig())
    top, index = scores.topk(16, dim=-1)
    torch.testing.assert_close(kept, torch.take_along_dim(candidates, index[..., None, None], 2))
    low, high = top.amin(-1, keepdim=True), top.amax(-1, keepdim=True)
    torch.testing.assert_close(weights, (top - low) / (high - low))  # eq:wtn
    assert bool((weights.amax(-1) == 1).all() & (weights.amin(-1) == 0).all())


def _batch(estimates: list[Estimate2D]) -> Estimate2D:
    """One-image estimates as one batch, unaries padded as the 2D stage pads them."""
    h = max(e.unaries.shape[2] for e in estimates)
    w = max(e.unaries.shape[3] for e in estimates)
    unaries = torch.full((len(estimates), NUM_JOINTS, h, w), float(np.log(LOG_EPS)))
    for i, e in enumerate(estimates):
        unaries[i, :, : e.unaries.shape[2], : e.unaries.shape[3]] = e.unaries[0]
    fields = [f.name for f in dataclasses.fields(Estimate2D)]
    cat = {
        f: torch.cat([getattr(e, f) for e in estimates])
        for f in fields
        if f != "unaries" and isinstance(getattr(estimates[0], f), torch.Tensor)
    }
    return dataclasses.replace(estimates[0], unaries=unaries, **cat)


def test_batch_results_equal_one_by_one_results(pipeline, images):
    # Given the same 2D stage output (whose own batching is the 2D stage's to test), every step
    # after it treats each image alone.
    singles = [pipeline.estimator.estimate([image]) for image in images[:3]]
    batch = pipeline.lift_estimate(_batch(singles))
    for i, single_estimate in enumerate(singles):
        single = pipeline.lift_estimate(single_estimate)
        torch.testing.assert_close(single.joints_2d[0], batch.joints_2d[i], atol=1e-3, rtol=0)
        torch.testing.assert_close(single.psm_energy[0], batch.psm_energy[i])
        # the batched pose fit sums in another order: millimetre differences (up to 1.2 mm on
        # these images with the bundled 2D model)
        torch.testing.assert_close(single.joints_3d[0], batch.joints_3d[i], atol=2.0, rtol=0)
        assert single.joint_set[0] == batch.joint_set[i]


def test_each_image_is_answered_as_its_own_people_and_min_score_ask(pipeline, images):
    both = pipeline.estimate(images[:2], people=["best", "all"], min_score=[0.2, 0.0])
    alone = [
        pipeline.estimate(images[:1]),
        pipeline.estimate(images[1:2], people="all", min_score=0.0),
    ]
    for image, single in enumerate(alone):
        mine = both.rows(torch.nonzero(both.image_index == image).view(-1))
        assert len(mine.score) == len(single.score) and mine.joint_set == single.joint_set
        torch.testing.assert_close(mine.score, single.score, atol=1e-4, rtol=0)
        torch.testing.assert_close(mine.box, single.box, atol=1e-2, rtol=0)
    assert len(both.people(0)) == 1
    with pytest.raises(ValueError, match="people"):
        pipeline.estimate(images[:2], people=["best"])
    with pytest.raises(ValueError, match="min_score"):
        pipeline.estimate(images[:2], min_score=[0.2, 1.5])


def test_energy_selection_and_single_set_variants_run(pipeline, images):
    pipeline.config = PipelineConfig(iterations=1, selection="energy")
    pipeline.lifter.configure(LifterConfig(joint_sets=("all",), weighting=False))
    try:
        res = pipeline.estimate(images[:2])
    finally:
        pipeline.config = PipelineConfig()
        pipeline.lifter.configure(LifterConfig())
    assert res.joint_set == ["all", "all"] and res.iterations == 1
    assert bool(torch.isfinite(res.joints_3d).all())


# The refinement against the 2D stage's own answer on the same images: on LSP test im1001-im1032
# it moved PCK@0.2 79.91 -> 79.46 % and the mean error 9.56 -> 9.68 px with the int8 joint
# network, 79.46 -> 79.69 % and 9.69 -> 9.59 px in float32 (on all 1000 images: docs/RESULTS.md,
# pipeline). 32 images are too few for either to move reliably; the gates catch a broken
# refinement (a bug that drew weak joints off the image cost 7 px on held-out images), not noise.
PCK_DROP = 0.02  # 9 of the 448 joints
ERROR_TOLERANCE_PX = 0.5


def test_bundled_model_refinement_does_not_make_2d_notably_worse(data_dir):
    if not (MODELS_DIR / "image2d" / "manifest.json").is_file():
        pytest.fail("the bundled 2D model models/image2d is missing")
    from ds3d.evaluation.metrics import pck, pixel_error

    ann = load_lsp(split="test").subset(range(32))
    pipeline = Pipeline.load()
    # the whole image as the crop, as `ds3d eval lsp-pipeline` runs it (no search)
    results = [
        pipeline.lift_estimate(
            pipeline.estimator.estimate([read_image(p) for p in ann.image_paths[i : i + 16]])
        )
        for i in (0, 16)
    ]
    gt = torch.from_numpy(ann.joints)
    initial = torch.cat([r.joints_2d_initial for r in results])
    refined = torch.cat([r.joints_2d for r in results])
    error = float(pixel_error(refined, gt).mean())
    assert error <= float(pixel_error(initial, gt).mean()) + ERROR_TOLERANCE_PX
    assert float(pck(refined, gt).mean()) >= float(pck(initial, gt).mean()) - PCK_DROP
    assert bool(torch.isfinite(torch.cat([r.joints_3d for r in results])).all())


@pytest.mark.slow
def test_the_bundled_confidences_say_how_often_joints_are_right(data_dir):
    """A confidence is the probability that the joint lies within PCK@0.2 of the truth
    (ds3d.confidence, fitted on held-out LSP train images): on LSP test images searched, about
    as many joints are right as the confidences say, and more of the surer ones."""
    from ds3d.evaluation.lsp import joint_outcomes

    pipeline = Pipeline.load()
    assert pipeline.joint_calibration is not None, "models/image2d/joint_calibration.json"
    raw, right = joint_outcomes(pipeline, load_lsp(split="test").subset(range(32)))
    confidence = pipeline.joint_calibration(raw)
    assert abs(float(confidence.mean()) - float(right.float().mean())) < 0.15
    sure = confidence >= 0.5
    assert float(right[sure].float().mean()) > float(right[~sure].float().mean()) + 0.2
    # the raw probabilities at one pixel say far less than how often joints are right
    assert float(raw.mean()) < float(right.float().mean()) - 0.4


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_the_pipeline_runs_on_cuda_as_on_the_cpu(images):
    """device="cuda": both stages of the bundled models on the GPU, people searched and in given
    boxes; about the same poses (the network's bfloat16 convolutions differ between the devices
    in their last bits)."""
    on_gpu = Pipeline.load(device="cuda")
    assert on_gpu.estimator.device.type == "cuda"
    assert all(forest.node_table.is_cuda for forest in on_gpu.estimator.layers)
    boxes = list(person_boxes(load_lsp(split="test").joints[: len(images)]))
    for bboxes in (None, boxes):
        cpu = Pipeline.load().estimate(images, bboxes)
        gpu = on_gpu.estimate(images, bboxes)
        assert gpu.joints_2d.device.type == "cpu" and gpu.joints_3d.device.type == "cpu"
        assert float((gpu.joints_2d - cpu.joints_2d).abs().median()) < 2.0  # px
        assert float((gpu.joints_3d - cpu.joints_3d).norm(dim=-1).median()) < 20.0  # mm


def test_a_box_the_image_cannot_hold_is_refused_before_any_work(pipeline, images):
    width = images[0].shape[1]
    for box, why in [((10, 10, 5, 40), "no area"), ((width + 1, 0, width + 9, 9), "outside")]:
        with pytest.raises(InvalidBox, match=why):
            pipeline.estimate(images[:1], bboxes=[box])
