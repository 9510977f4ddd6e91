"""Per-joint confidence that means something to a user: the probability that the joint lies
within PCK@0.2 of the truth (0.2 times the person's torso diameter).

The 2D stage's probability of a joint at the answered pixel (PipelineResult's raw confidence) is
a probability at one pixel among thousands: 0.02-0.14 on LSP, whatever the joint's chance of being
right. JointCalibration maps it per joint type by a logistic fit on its logarithm, fitted on
held-out images (`ds3d eval joint-confidence --split train --start 700 --fit`, LSP train
im0701-im1000) and stored beside the 2D model (image2d/joint_calibration.json). How well
confidences match how often joints are right: ds3d.evaluation.metrics.expected_calibration_error
(docs/RESULTS.md, joint confidence).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from ds3d.skeleton import JOINT_NAMES, NUM_JOINTS

FILE_NAME = "joint_calibration.json"
# Added to the raw probability before the log, which keeps the log finite where the 2D stage's
# probability is 0 (it subtracts its own floor, image2d.result.LOG_EPS, from its unaries).
PROBABILITY_FLOOR = 1e-6


@dataclass(frozen=True)
class JointCalibration:
    """P(joint j within PCK@0.2) = sigmoid(intercept[j] + slope[j] * log(p + PROBABILITY_FLOOR))
    for the 2D stage's probability p of joint j at the answered pixel; intercept, slope (14,)."""

    intercept: torch.Tensor
    slope: torch.Tensor

    def __call__(self, probability: torch.Tensor) -> torch.Tensor:
        """(N, 14) raw probabilities in [0, 1] -> (N, 14) calibrated, float32, on their device."""
        feature = (probability.float().clamp(0, 1) + PROBABILITY_FLOOR).log()
        a, b = (t.to(feature.device) for t in (self.intercept, self.slope))
        return torch.sigmoid(a + b * feature)

    def save(self, path: Path) -> None:
        rows = zip(JOINT_NAMES, self.intercept.tolist(), self.slope.tolist(), strict=True)
        table = {name: {"intercept": a, "slope": b} for name, a, b in rows}
        document = {"feature": f"log(p + {PROBABILITY_FLOOR:g})", "joints": table}
        path.write_text(json.dumps(document, indent=2) + "\n")

    @classmethod
    def load(cls, path: Path) -> JointCalibration:
        table = json.loads(path.read_text())["joints"]
        rows = [table[name] for name in JOINT_NAMES]
        return cls(
            torch.tensor([r["intercept"] for r in rows], dtype=torch.float32),
            torch.tensor([r["slope"] for r in rows], dtype=torch.float32),
        )


def fit_joint_calibration(
    probability: torch.Tensor, correct: torch.Tensor, iterations: int = 50, ridge: float = 1e-3
) -> JointCalibration:
    """The logistic fit of JointCalibration: probability (N, 14) raw, correct (N, 14) bool (the
    joint within PCK@0.2) -> the (intercept, slope) per joint of least log-loss, by Newton's
    method on all 14 joints at once (`ridge` on the Hessian keeps a joint that is always right,
    or always wrong, finite)."""
    if probability.shape != correct.shape or probability.shape[-1] != NUM_JOINTS:
        raise ValueError(f"probability {tuple(probability.shape)}, correct {tuple(correct.shape)}")
    feature = (probability.double().clamp(0, 1) + PROBABILITY_FLOOR).log().T  # (14, N)
    design = torch.stack([torch.ones_like(feature), feature], -1)  # (14, N, 2)
    target = correct.double().T
    theta = torch.zeros(NUM_JOINTS, 2, dtype=torch.float64)
    eye = torch.eye(2, dtype=torch.float64)
    for _ in range(iterations):
        p = torch.sigmoid((design @ theta[..., None])[..., 0])
        gradient = (design * (p - target)[..., None]).sum(1) + ridge * theta
        hessian = design.transpose(1, 2) @ (design * (p * (1 - p))[..., None]) + ridge * eye
        theta = theta - torch.linalg.solve(hessian, gradient)
    return JointCalibration(theta[:, 0].float(), theta[:, 1].float())
