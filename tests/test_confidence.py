"""Per-joint confidence as a probability (ds3d.confidence): the fit, its file; and the measures
of calibration (ds3d.evaluation.metrics)."""

from __future__ import annotations

import torch

from ds3d.confidence import JointCalibration, fit_joint_calibration
from ds3d.evaluation.metrics import expected_calibration_error, reliability
from ds3d.skeleton import NUM_JOINTS


def _outcomes(calibration: JointCalibration, n: int, seed: int = 0):
    """Raw probabilities and outcomes drawn from `calibration`: a joint is right with the
    probability it says."""
    gen = torch.Generator().manual_seed(seed)
    raw = 10 ** (-3 * torch.rand(n, NUM_JOINTS, generator=gen))  # 0.001 to 1
    right = torch.rand(n, NUM_JOINTS, generator=gen) < calibration(raw)
    return raw, right


def test_the_fit_recovers_the_calibration_that_drew_the_outcomes():
    truth = JointCalibration(torch.linspace(1.0, 3.0, NUM_JOINTS), torch.linspace(0.3, 1.0, 14))
    raw, right = _outcomes(truth, 20_000)
    fitted = fit_joint_calibration(raw, right)
    torch.testing.assert_close(fitted.intercept, truth.intercept, atol=0.25, rtol=0)
    torch.testing.assert_close(fitted.slope, truth.slope, atol=0.08, rtol=0)
    # as calibrated as the truth on fresh outcomes; the raw probabilities are not
    raw, right = _outcomes(truth, 5_000, seed=1)
    assert expected_calibration_error(fitted(raw), right) < 0.03
    assert expected_calibration_error(raw, right) > 0.2


def test_a_joint_always_right_or_always_wrong_gets_a_finite_certain_calibration():
    raw = torch.rand(500, NUM_JOINTS)
    right = torch.zeros(500, NUM_JOINTS, dtype=torch.bool)
    right[:, 0] = True
    fitted = fit_joint_calibration(raw, right)
    assert torch.isfinite(fitted.intercept).all() and torch.isfinite(fitted.slope).all()
    confidence = fitted(raw)
    assert (confidence[:, 0] > 0.95).all() and (confidence[:, 1:] < 0.05).all()


def test_the_calibration_round_trips_through_its_file(tmp_path):
    calibration = JointCalibration(torch.randn(NUM_JOINTS), torch.rand(NUM_JOINTS))
    calibration.save(tmp_path / "c.json")
    loaded = JointCalibration.load(tmp_path / "c.json")
    raw = torch.rand(7, NUM_JOINTS)
    torch.testing.assert_close(loaded(raw), calibration(raw))


def test_reliability_bins_and_ece_count_what_was_said_and_what_was_right():
    confidence = torch.tensor([0.05, 0.05, 0.95, 0.95, 0.55, 0.55])
    right = torch.tensor([False, False, True, True, True, False])
    rows = reliability(confidence, right, bins=10)
    assert [(r["low"], r["count"], r["accuracy"]) for r in rows] == [
        (0.0, 2, 0.0), (0.5, 2, 0.5), (0.9, 2, 1.0)
    ]  # fmt: skip
    # |0.05 - 0| + |0.55 - 0.5| + |0.95 - 1|, a third each
    assert abs(expected_calibration_error(confidence, right) - 0.05) < 1e-6
