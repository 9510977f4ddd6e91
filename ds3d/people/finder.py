"""Finding people, from images to the poses answered: which crops of each image go through the 2D
stage (PeopleFinder.find) and, once it has posed them, who is answered (PeopleFinder.answer).

    find     a box given is its own crop; an image without one is searched (ds3d.people.search),
             its proposals each a crop of known scale, the whole image one more where the search
             proposes at most one person
    answer   per image, non-maximum suppression of the crops' poses by person score (their
             boxes overlapping, or one person found twice: ds3d.people.same_person), the best
             ("best") or those scoring min_score ("all"), then the weak proposals apart from them

pose_and_answer runs the 2D stage (the caller's) between the two, the weak proposals after the
others and only where they lie apart from the people those answered.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ds3d.boxes import iou, person_boxes, suppress
from ds3d.errors import DataFormatError
from ds3d.image2d.crops import image_share
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.jointnet import ScaledLogits
from ds3d.image2d.result import Estimate2D, gather_rows
from ds3d.inputs import ImageInput
from ds3d.people.same_person import joints_on_bones, shared_joints
from ds3d.people.score import PersonScore, person_evidence
from ds3d.people.search import Proposals, SearchParams, propose


@dataclass(frozen=True)
class Candidate:
    """A region of an image that goes through the 2D stage as its own crop: the image (an index
    into the batch), a person box (x0, y0, x1, y1) px, whether the box was given (its person is
    answered whatever its score), and whether its scale is known (a search proposal's, found at
    its level) or left to the 2D stage's pyramid; views: the joint network's maps of the image
    that the search computed (Proposals.levels), off which the 2D stage reads the maps that
    choose the crop's scale; proposal_score: the search's root score of the proposal it is the
    crop of (NaN: none, a box given or the whole image); weak: a proposal below proposal_floor
    (SearchParams.weak_floor), answered only apart from the people answered."""

    image: int
    box: np.ndarray
    given: bool
    scale_known: bool
    views: Sequence[ScaledLogits] = ()
    proposal_score: float = math.nan
    weak: bool = False


@dataclass(frozen=True)
class Answer:
    """Who is answered of C candidates posed: rows (N,) int64, the candidates answered, image by
    image, best first; found (C,) bool, a box given or a score of at least the image's
    min_score; score (C,) float32, the person score; evidence (C, 3) float64, what it weighs
    (ds3d.people.score.person_evidence)."""

    rows: torch.Tensor
    found: torch.Tensor
    score: torch.Tensor
    evidence: torch.Tensor


class PeopleFinder:
    """The people of images, with a 2D model (`estimator`, whose joint network searches), the
    search's settings and the model's person score (None: a model without one, which answers
    people in the boxes given but cannot search: ds3d.people.score). `find` gives the crops,
    `answer` who of them is answered."""

    def __init__(self, estimator: PoseEstimator2D, params: SearchParams, score: PersonScore | None):
        self.estimator = estimator
        self.params = params
        self.score = score

    def scores(self, evidence: torch.Tensor) -> torch.Tensor:
        """(C, 3) person_evidence -> (C,) float32 person scores (NaN: the model has none)."""
        if self.score is None:
            return torch.full((len(evidence),), torch.nan)
        return self.score(evidence)

    def _require_score(self) -> None:
        """Raises DataFormatError where the model has no person score: its people cannot be
        told from the rest."""
        if self.score is None:
            raise DataFormatError(
                "the 2D model has no person_score.json, so it cannot tell people apart: fit it "
                "with `ds3d eval people --split train --start 700 --fit` (models/MODEL_CARD.md)"
            )

    def find(
        self, inputs: Sequence[ImageInput], timings: dict[str, float] | None = None
    ) -> list[Candidate]:
        """The crops of B checked images: each given box, whose scale the 2D stage chooses; for
        an image without one, its search's proposals, whose scale the search has found (an image
        asked for its best person sends its best proposal alone), and, where it proposes at most
        one person, the whole image as one more crop, which finds people the image's edge cuts,
        unless the proposal's crop already holds most of the image (whole_image_cover).
        (Estimating the other proposals too and answering the best by the 2D stage's score gave
        79.76 against 79.93 % PCK held out, ds3d eval lsp-pipeline --searched, at twice the 2D
        stage's time on every image with a second proposal.) timings: as propose's."""
        searched = [i for i, item in enumerate(inputs) if item.bbox is None]
        if searched:
            self._require_score()
        best_only = [inputs[i].people == "best" for i in searched]
        proposals = propose(
            self.estimator, [inputs[i].image for i in searched], self.params, best_only, timings
        )
        out = [
            Candidate(i, item.bbox, True, False)
            for i, item in enumerate(inputs)
            if item.bbox is not None
        ]
        for i, found in zip(searched, proposals, strict=True):
            height, width = inputs[i].image.shape[:2]
            proposed = self._proposals_on(i, found)
            strong = [c.box for c in proposed if not c.weak]
            if inputs[i].people == "best":
                proposed = proposed[:1]
            out += proposed
            # The whole image is one person's crop: where the search found several people, its
            # one pose would join them.
            shares = [image_share(box, width, height, self.estimator.params) for box in strong]
            if len(strong) <= 1 and not any(s >= self.params.whole_image_cover for s in shares):
                whole = np.array([0, 0, width, height], np.float32)
                out.append(Candidate(i, whole, False, False, found.levels))
        return out

    def _proposals_on(self, image: int, proposals: Proposals) -> list[Candidate]:
        """The candidates of image `image`'s proposals that go on to the 2D stage, best first,
        each the box of the proposal's joints (so that the crop's base scale is the proposal's):
        the best max_people of those scoring proposal_floor, and always the best; then, weak,
        the best weak_people of the others scoring weak_floor. Only proposals whose box has an
        area: a pose whose joints all share one column or row (a PSM collapsed against the edge
        of a level's maps) is nobody, and a crop needs an area."""
        params, scores = self.params, proposals.scores
        boxes = np.concatenate([proposals.poses.min(1), proposals.poses.max(1)], 1)
        area = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        strong = scores >= params.proposal_floor
        strong[:1] = True
        weak = ~strong & (scores >= params.weak_floor)
        chosen = [
            (k, kind)
            for kind, among, most in (
                (False, strong, params.max_people),
                (True, weak, params.weak_people),
            )
            for k in np.nonzero(among & area)[0][:most]
        ]
        return [
            Candidate(image, boxes[k], False, True, (), float(scores[k]), kind)
            for k, kind in chosen
        ]

    def pose_and_answer(
        self,
        inputs: Sequence[ImageInput],
        candidates: list[Candidate],
        pose_2d: Callable[[list[Candidate]], Estimate2D],
    ) -> tuple[list[Candidate], Estimate2D, Answer]:
        """The candidates (find's) posed by the 2D stage (pose_2d: candidates -> their
        Estimate2D, in their order) and answered (answer), in two rounds: first all but the
        weak ones; then the weak ones whose box overlaps nobody those answered by more than
        weak_apart, the others being second readings of them that answer would not answer.
        Returns the candidates posed, in the order of their estimate, and the answer."""
        first = [c for c in candidates if not c.weak]
        estimate = pose_2d(first)
        answer = self.answer(inputs, first, estimate)
        weak = self._apart([c for c in candidates if c.weak], first, estimate, answer)
        if not weak:
            return first, estimate, answer
        posed = first + weak
        rounds = [
            (torch.arange(len(first)), estimate),
            (torch.arange(len(first), len(posed)), pose_2d(weak)),
        ]
        estimate = gather_rows(rounds, len(posed))
        return posed, estimate, self.answer(inputs, posed, estimate)

    def _apart(
        self, weak: list[Candidate], posed: list[Candidate], estimate: Estimate2D, answer: Answer
    ) -> list[Candidate]:
        """The weak candidates whose box (widened as person_boxes widens a pose's) overlaps no
        person answered in its image, of those `posed` (estimate, answer), by more than
        weak_apart (IoU)."""
        boxes = person_boxes(estimate.joints_2d[answer.rows].cpu().numpy())
        image = np.array([posed[k].image for k in answer.rows.tolist()], dtype=np.int64)
        out = []
        for candidate in weak:
            others = boxes[image == candidate.image]
            box = person_boxes(candidate.box.reshape(1, 2, 2))
            if not len(others) or iou(box, others).max() <= self.params.weak_apart:
                out.append(candidate)
        return out

    def evidence(
        self, estimate: Estimate2D, candidates: Sequence[Candidate] | None = None
    ) -> torch.Tensor:
        """(C, 3) float64 on the CPU: the person_evidence of the 2D stage's C poses (None: of
        crops that no proposal found)."""
        typical = self.estimator.mixtures.typical_lengths()
        root = torch.full((len(estimate.score),), math.nan, dtype=torch.float64)
        if candidates is not None:
            root = torch.tensor([c.proposal_score for c in candidates], dtype=torch.float64)
        return person_evidence(estimate.score, estimate.joints_2d, typical, root)

    def answer(
        self, inputs: Sequence[ImageInput], candidates: list[Candidate], estimate: Estimate2D
    ) -> Answer:
        """Who is answered of the candidates, once the 2D stage has posed them (estimate, in
        their order), settled on their 2D poses so that only they are lifted: per image, after
        non-maximum suppression of its candidates by score (their pose boxes overlapping by
        `overlap`, their poses sharing same_person_joints joints, or one's on_bones_joints
        joints lying on the other's bones: one person found twice), the best one (its input's
        people "best") or those found ("all"); then, best score first, the weak candidates
        found whose box overlaps no answered one's by more than weak_overlap (IoU): a weak
        proposal is a person the search was unsure of, answered where nobody found stands, not
        as a second reading of them."""
        evidence = self.evidence(estimate, candidates)
        score = self.scores(evidence)
        # On the CPU: a few numbers per candidate, settled with NumPy. A box given is answered
        # whatever its score, alone in its image (a model without a person score, whose scores
        # are NaN, answers only boxes given).
        rank = score.nan_to_num(1.0)
        image_index = torch.tensor([c.image for c in candidates], dtype=torch.long)
        given = torch.tensor([c.given for c in candidates])
        floor = torch.tensor([item.min_score for item in inputs], dtype=rank.dtype)
        found = given | (rank >= floor[image_index])
        poses = estimate.joints_2d.cpu().numpy()
        weak = torch.tensor([c.weak for c in candidates], dtype=torch.bool)
        rows = [torch.zeros(0, dtype=torch.long)]
        for image in image_index.unique().tolist():
            own = torch.nonzero(image_index == image).view(-1)
            if inputs[image].people == "best":  # the suppression keeps the best first: it alone
                rows.append(own[rank[own].argmax()].view(1))
            else:
                rows.append(self._everyone(poses, own, weak, rank, found))
        return Answer(torch.cat(rows), found, score, evidence)

    def _everyone(
        self,
        poses: np.ndarray,
        own: torch.Tensor,
        weak: torch.Tensor,
        rank: torch.Tensor,
        found: torch.Tensor,
    ) -> torch.Tensor:
        """The candidates `own` (one image's, of those posed as poses (C, 14, 2) px) answered
        when the image asks for every person, best first: the strong ones that _distinct keeps,
        then the weak ones found apart from them. weak, rank, found: (C,) of all candidates."""
        answered = self._distinct(poses, own[~weak[own]].numpy(), rank, found)
        boxes = person_boxes(poses)
        unsure = own[weak[own]]
        for k in unsure[rank[unsure].argsort(descending=True)].tolist():
            overlap = iou(boxes[k], boxes[answered]).max() if answered else 0.0
            if found[k] and overlap <= self.params.weak_overlap:
                answered.append(k)
        answered.sort(key=lambda k: -float(rank[k]))
        return torch.tensor(answered, dtype=torch.long)

    def _distinct(
        self, poses: np.ndarray, rows: np.ndarray, rank: torch.Tensor, found: torch.Tensor
    ) -> list[int]:
        """Of the candidates `rows` (posed as poses[rows], (R, 14, 2) px), the found ones that
        non-maximum suppression by rank keeps: no two of them one person."""
        params, own = self.params, poses[rows]
        shared = shared_joints(own, params.same_person_radius)
        on_bones = joints_on_bones(own, params.on_bones_radius)
        same = (shared >= params.same_person_joints) | (on_bones >= params.on_bones_joints)
        kept = rows[suppress(person_boxes(own), rank[rows].numpy(), params.overlap, same | same.T)]
        return kept[found[kept].numpy()].tolist()
