"""The person score: the probability that a crop the 2D stage posed holds a person.

It weighs three things of each crop (person_evidence): the 2D stage's PSM score of its pose, how
far out of proportion its limbs are (limb_stretch), and the search's root score of the proposal
it is the crop of. The weights are a logistic fit to one 2D model's poses, so they travel with
that model: `person_score.json` in its folder, written by `ds3d eval people --fit` (fitted on
held-out canvases only, ds3d.evaluation.people) and read when the model is loaded. A model without
one cannot score people, and says so, rather than borrow another model's weights.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ds3d.errors import DataFormatError
from ds3d.skeleton import LIMBS

FILE_NAME = "person_score.json"


@dataclass(frozen=True)
class PersonScore:
    """P(a person) = sigmoid((psm - psm_center) / psm_width - stretch_weight * stretch +
    root_weight * (root - root_reference)) of a crop's person_evidence (psm, stretch, root).
    root_reference: the root score that a crop of no proposal (a box given, the whole image)
    counts as; the search's proposal floor when the weights were fitted."""

    psm_center: float
    psm_width: float
    stretch_weight: float
    root_weight: float
    root_reference: float

    def __call__(self, evidence: torch.Tensor) -> torch.Tensor:
        """(B, 3) person_evidence -> (B,) float32 probabilities, on the evidence's device."""
        psm, stretch, root = evidence.double().unbind(-1)
        root = torch.nan_to_num(root, nan=self.root_reference)
        z = (psm - self.psm_center) / self.psm_width - self.stretch_weight * stretch
        return torch.sigmoid(z + self.root_weight * (root - self.root_reference)).float()

    def save(self, model_dir: Path) -> None:
        """Writes model_dir/person_score.json."""
        (Path(model_dir) / FILE_NAME).write_text(json.dumps(asdict(self), indent=2) + "\n")

    @classmethod
    def load(cls, model_dir: Path) -> PersonScore | None:
        """The weights of model_dir/person_score.json; None where the model has none. Raises
        DataFormatError for a file that does not hold them."""
        path = Path(model_dir) / FILE_NAME
        if not path.exists():
            return None
        try:
            return cls(**{k: float(v) for k, v in json.loads(path.read_text()).items()})
        except (TypeError, ValueError) as err:
            raise DataFormatError(f"{path}: not a person score ({err})") from err


def limb_stretch(joints_2d: torch.Tensor, typical: torch.Tensor) -> torch.Tensor:
    """How far out of proportion a pose's limbs are: joints_2d (B, 14, 2) px, typical (13,) each
    limb's typical length (PairwiseMixtures.typical_lengths, ds3d.skeleton.LIMBS order) ->
    (B,) the log of the longest limb relative to its typical length over the median limb's, 0
    for limbs in proportion. The PSM scores each limb on its own, so it can answer a small
    person with a limb drawn out along an edge, or a person's legs as a whole one: such poses
    are far out of proportion, people seldom (foreshortening shortens limbs, and the median
    takes the person's scale)."""
    child, parent = (torch.tensor(side) for side in zip(*LIMBS, strict=True))
    relative = (joints_2d[:, child] - joints_2d[:, parent]).norm(dim=-1) / typical  # (B, 13)
    median = relative.median(dim=-1).values.clamp_min(1e-6)
    return (relative.amax(dim=-1) / median).clamp_min(1.0).log()


def person_evidence(
    psm_score: torch.Tensor, joints_2d: torch.Tensor, typical: torch.Tensor, root: torch.Tensor
) -> torch.Tensor:
    """What the person score weighs, for B crops: the 2D stage's PSM score of its pose
    (Estimate2D.score) (B,), the pose's limb_stretch (joints_2d (B, 14, 2) px against the limbs'
    typical lengths (13,)), and the root score (B,) of the search's proposal that the crop is of
    (Proposals.scores; NaN where none is) -> (B, 3) float64 on the CPU. The root score says how
    the person stands out on their level of the whole image; the PSM score says how the pose
    fits its crop, where it may borrow a neighbour's limbs."""
    stretch = limb_stretch(joints_2d.float().cpu(), typical.float().cpu())
    columns = (psm_score.cpu(), stretch, root.cpu())
    return torch.stack([c.double() for c in columns], -1)


def fit_person_score(
    evidence: np.ndarray, is_person: np.ndarray, root_reference: float, iterations: int = 50
) -> PersonScore:
    """The PersonScore of least log-loss on crops whose person_evidence (N, 3) and whether each
    is a person (N,) bool are known: logistic regression by Newton's method (convex), the PSM
    score standardised and the root score in hundreds so that the steps are well scaled; a crop
    of no proposal (NaN root) counts at root_reference. A small ridge keeps it finite where the
    classes separate."""
    x = np.asarray(evidence, np.float64).reshape(-1, 3)
    y = np.asarray(is_person, np.float64)
    mean, sd = x[:, 0].mean(), max(x[:, 0].std(), 1e-9)
    root = (np.nan_to_num(x[:, 2], nan=root_reference) - root_reference) / 100
    design = np.stack([(x[:, 0] - mean) / sd, x[:, 1], root, np.ones(len(y))], 1)
    theta = np.array([1.0, 0.0, 0.0, 0.0])
    for _ in range(iterations):
        p = 1 / (1 + np.exp(-design @ theta))
        hessian = design.T @ ((p * (1 - p) + 1e-9)[:, None] * design) + 1e-6 * np.eye(4)
        theta = theta - np.linalg.solve(hessian, design.T @ (p - y))
    a, c, r, b = theta
    width = sd / a
    return PersonScore(
        psm_center=round(float(mean - b * width), 2),
        psm_width=round(float(width), 2),
        stretch_weight=round(float(-c), 3),
        root_weight=round(float(r / 100), 5),
        root_reference=float(root_reference),
    )
