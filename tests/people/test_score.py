"""The person score (ds3d.people.score): what it weighs, its fit, and its numbers read from the
2D model they were fitted to."""

import shutil

import numpy as np
import pytest
import torch

from ds3d.errors import DataFormatError
from ds3d.people.score import PersonScore, fit_person_score, limb_stretch, person_evidence
from ds3d.skeleton import LIMBS, NUM_JOINTS
from ds3d.util.paths import MODELS_DIR


def test_limbs_out_of_proportion_stretch_a_pose_and_lower_its_probability():
    typical = torch.tensor([30.0 + 3 * k for k in range(len(LIMBS))])
    pose = torch.zeros(NUM_JOINTS, 2)  # a tree of limbs of the typical lengths, x 0.7
    for child, parent in sorted(LIMBS, key=lambda limb: _depth(limb[0])):
        pose[child] = pose[parent] + 0.7 * typical[LIMBS.index((child, parent))] * torch.tensor(
            [np.cos(child), np.sin(child)], dtype=torch.float32
        )
    drawn_out = pose.clone()  # the left ankle's limb three times its length
    ankle = LIMBS.index(next(limb for limb in LIMBS if limb[0] == 5))
    drawn_out[5] = pose[LIMBS[ankle][1]] + 3 * (pose[5] - pose[LIMBS[ankle][1]])
    stretch = limb_stretch(torch.stack([pose, drawn_out, pose * 4 + 100]), typical)
    torch.testing.assert_close(stretch[[0, 2]], torch.zeros(2), atol=1e-5, rtol=0)
    torch.testing.assert_close(stretch[1], torch.tensor(float(np.log(3))), atol=1e-5, rtol=0)
    assert limb_stretch(torch.zeros(1, NUM_JOINTS, 2), typical).item() == 0  # no limbs at all
    score = PersonScore(-260.0, 30.0, 1.5, 0.02, 120.0)
    poses, same, unproposed = (
        torch.stack([pose, drawn_out]),
        torch.full((2,), -250.0),
        torch.full((2,), torch.nan),
    )

    def probability(psm: torch.Tensor, root: torch.Tensor) -> torch.Tensor:
        return score(person_evidence(psm, poses, typical, root))

    drawn_out_lower = probability(same, unproposed)
    assert drawn_out_lower[1] < drawn_out_lower[0]
    assert (probability(same + 20, unproposed) > drawn_out_lower).all()
    # a box no proposal found counts as one at the floor; a person standing out more is likelier
    at_floor = torch.full((2,), score.root_reference)
    torch.testing.assert_close(probability(same, at_floor), drawn_out_lower)
    assert (probability(same, at_floor + 50) > drawn_out_lower).all()


def test_the_fit_is_the_likeliest_logistic_of_the_evidence():
    """Evidence drawn from a known PersonScore, labels drawn from its probabilities: the fit
    makes them at least as likely as the score that drew them (up to its rounding), and finds
    the signs of its weights."""
    rng = np.random.default_rng(0)
    n = 4000
    evidence = np.stack(
        [rng.normal(-280, 30, n), rng.exponential(0.3, n), rng.normal(120, 30, n)], 1
    )
    evidence[::7, 2] = np.nan  # crops of no proposal: at the reference
    truth = PersonScore(-280.0, 20.0, 2.0, 0.03, 120.0)
    p = truth(torch.from_numpy(evidence)).double().numpy()
    person = rng.random(n) < p
    fitted = fit_person_score(evidence, person, root_reference=120.0)

    def log_loss(score: PersonScore) -> float:
        q = score(torch.from_numpy(evidence)).double().numpy().clip(1e-12, 1 - 1e-12)
        return float(-(person * np.log(q) + (1 - person) * np.log(1 - q)).mean())

    assert log_loss(fitted) <= log_loss(truth) + 1e-3
    assert fitted.psm_width > 0 and fitted.stretch_weight > 0 and fitted.root_weight > 0


def test_the_score_is_read_from_its_model_and_a_model_without_one_says_so(tmp_path):
    truth = PersonScore(-280.0, 20.0, 2.0, 0.03, 120.0)
    truth.save(tmp_path)
    assert PersonScore.load(tmp_path) == truth
    assert PersonScore.load(tmp_path / "elsewhere") is None
    (tmp_path / "person_score.json").write_text('{"psm_center": "x"}')
    with pytest.raises(DataFormatError):
        PersonScore.load(tmp_path)


def test_a_model_folder_with_other_numbers_scores_people_otherwise(tmp_path):
    """The person score of a Pipeline is the one in its 2D model's folder: the same model with
    another person_score.json answers the same poses with other scores; without one, it answers
    boxes given and refuses to search."""
    from ds3d.pipeline import Pipeline

    models = tmp_path / "models"
    shutil.copytree(MODELS_DIR / "image2d", models / "image2d")
    (models / "posedb").symlink_to(MODELS_DIR / "posedb")
    image = (np.arange(240 * 160 * 3) % 251).astype(np.uint8).reshape(240, 160, 3)
    box = [20, 20, 140, 220]
    bundled = Pipeline.load(models).estimate([image], bboxes=[box])
    bundled_score = PersonScore.load(models / "image2d")
    assert bundled_score is not None
    other = PersonScore(bundled_score.psm_center + 50, bundled_score.psm_width, 0.0, 0.0, 120.0)
    other.save(models / "image2d")
    refitted = Pipeline.load(models).estimate([image], bboxes=[box])
    torch.testing.assert_close(refitted.joints_3d, bundled.joints_3d)
    assert float(refitted.score[0]) < float(bundled.score[0])
    (models / "image2d" / "person_score.json").unlink()
    unscored = Pipeline.load(models)
    assert unscored.estimate([image], bboxes=[box]).score.isnan().all()
    with pytest.raises(DataFormatError, match=r"person_score\.json"):
        unscored.estimate([image])


def _depth(joint: int) -> int:
    """How many limbs lie between a joint and the root."""
    parents = dict(LIMBS)
    return 0 if joint not in parents else 1 + _depth(parents[joint])
