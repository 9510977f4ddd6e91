"""Which crops of an image go through the 2D stage, and who of them is answered
(ds3d.people.finder), on proposals made up here."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.result import Estimate2D
from ds3d.inputs import ImageInput
from ds3d.people.finder import Candidate, PeopleFinder
from ds3d.people.score import PersonScore
from ds3d.people.search import Proposals, SearchParams
from ds3d.skeleton import NUM_JOINTS

SCORE = PersonScore(-304.45, 24.17, 1.478, 0.02575, 120.0)


def test_proposals_without_area_are_not_cropped(monkeypatch):
    """A search proposal whose joints share one column (a PSM collapsed against a level's edge)
    has no box to crop: it is dropped, even as the best one."""
    flat = np.zeros((NUM_JOINTS, 2), np.float32)
    flat[:, 1] = np.linspace(38.0, 456.0, NUM_JOINTS)  # x = 0 for every joint
    person = np.stack([np.linspace(10.0, 60.0, NUM_JOINTS), np.linspace(5.0, 90.0, NUM_JOINTS)], 1)
    found = Proposals(np.stack([flat, person]), np.array([300.0, 200.0], np.float32), [])
    image = np.zeros((480, 640, 3), np.uint8)
    boxes = [c.box.tolist() for c in _candidates(monkeypatch, found, image)]
    assert boxes == [[10.0, 5.0, 60.0, 90.0], [0.0, 0.0, 640.0, 480.0]]


def test_the_whole_image_is_no_second_crop_of_a_person_who_fills_it(monkeypatch):
    """A photo that is a tight crop around its person: the proposal's crop holds the whole
    image, which is then not estimated again as a crop of its own; a smaller person leaves the
    whole image its own crop (it finds people the image's edge cuts)."""
    image = np.zeros((200, 120, 3), np.uint8)
    ys, xs = np.linspace(15.0, 185.0, NUM_JOINTS), np.linspace(25.0, 95.0, NUM_JOINTS)
    filling = np.stack([xs, ys], 1)
    found = Proposals(filling[None], np.array([300.0], np.float32), [])
    assert [c.box.tolist() for c in _candidates(monkeypatch, found, image)] == [
        [25.0, 15.0, 95.0, 185.0]
    ]
    small = 0.3 * filling + 40.0
    found = Proposals(small[None], np.array([300.0], np.float32), [])
    assert len(_candidates(monkeypatch, found, image)) == 2


def test_an_image_asked_for_its_best_person_has_its_best_proposal_alone_estimated(monkeypatch):
    """...and where the search proposes several people, the whole image is no crop of its
    own, for "best" too: its one pose would join them."""
    image = np.zeros((480, 640, 3), np.uint8)
    person = np.stack([np.linspace(10.0, 60.0, NUM_JOINTS), np.linspace(5.0, 90.0, NUM_JOINTS)], 1)
    found = Proposals(np.stack([person, person + 300.0]), np.array([300.0, 200.0], np.float32), [])
    every = [c.box.tolist() for c in _candidates(monkeypatch, found, image, "all")]
    assert every == [[10.0, 5.0, 60.0, 90.0], [310.0, 305.0, 360.0, 390.0]]
    assert [c.box.tolist() for c in _candidates(monkeypatch, found, image, "best")] == [every[0]]
    alone = Proposals(person[None], np.array([300.0], np.float32), [])
    whole = [0.0, 0.0, 640.0, 480.0]
    assert [c.box.tolist() for c in _candidates(monkeypatch, alone, image, "best")] == [
        every[0],
        whole,
    ]


def test_proposals_below_the_floor_go_on_as_weak_candidates_after_the_others(monkeypatch):
    """The best max_people proposals scoring proposal_floor (and always the best), then the
    best weak_people of those scoring weak_floor, flagged weak, with their root scores."""
    image = np.zeros((480, 640, 3), np.uint8)
    person = np.stack([np.linspace(10.0, 60.0, NUM_JOINTS), np.linspace(5.0, 90.0, NUM_JOINTS)], 1)
    poses = np.stack([person + 100.0 * k for k in range(4)])
    found = Proposals(poses, np.array([300.0, 150.0, 90.0, 50.0], np.float32), [])
    chosen = _candidates(monkeypatch, found, image)
    assert [(c.proposal_score, c.weak) for c in chosen] == [
        (300.0, False),
        (150.0, False),
        (90.0, True),
    ]
    assert [c.box.tolist() for c in chosen] == [
        [10.0 + 100 * k, 5.0 + 100 * k, 60.0 + 100 * k, 90.0 + 100 * k] for k in range(3)
    ]


def test_a_weak_candidate_is_answered_only_apart_from_the_people_answered():
    """A weak proposal (below proposal_floor) found near an answered person is mostly a second
    reading of them: it is answered only where its box overlaps nobody answered by more than
    weak_overlap, and like any other only where it scores min_score."""
    person = np.stack([np.linspace(10.0, 60.0, NUM_JOINTS), np.linspace(5.0, 90.0, NUM_JOINTS)], 1)
    shifts = [0.0, 20.0, 200.0, 400.0]  # a strong person; weak: beside them, apart, apart
    joints = torch.from_numpy(np.stack([person + s for s in shifts])).float()
    candidates = [
        Candidate(0, np.zeros(4), False, True, (), score, weak)
        for score, weak in ((300.0, False), (90.0, True), (90.0, True), (90.0, True))
    ]
    sure, unsure = -200.0, -500.0  # PSM scores: a person, nobody
    psm = torch.tensor([sure, sure, sure, unsure], dtype=torch.float64)
    evidence = torch.stack(
        [psm, torch.zeros(4, dtype=torch.float64), torch.full((4,), 90.0, dtype=torch.float64)], -1
    )
    evidence[0, 2] = 300.0
    finder = PeopleFinder(SimpleNamespace(), SearchParams(), SCORE)  # type: ignore[arg-type]
    finder.evidence = lambda estimate, candidates: evidence  # type: ignore[method-assign]
    estimate = SimpleNamespace(joints_2d=joints)
    inputs = [ImageInput(np.zeros((480, 640, 3), np.uint8), people="all", min_score=0.5)]
    answer = finder.answer(inputs, candidates, estimate)  # type: ignore[arg-type]
    assert answer.rows.tolist() == [0, 2] and answer.found.tolist() == [True, True, True, False]


def test_weak_proposals_are_posed_only_apart_from_the_people_the_others_answered():
    """pose_and_answer poses the weak proposals after the others, and only those whose box lies
    apart from the people the others answered: one on an answered person would not be answered
    (weak_overlap), so the 2D stage is spared it."""
    person = np.stack([np.linspace(10.0, 60.0, NUM_JOINTS), np.linspace(5.0, 90.0, NUM_JOINTS)], 1)

    def proposal(shift: float, score: float, weak: bool) -> Candidate:
        box = np.array([10.0, 5.0, 60.0, 90.0], np.float32) + shift
        return Candidate(0, box, False, True, (), score, weak)

    rounds: list[list[float]] = []

    def pose_2d(chosen: list[Candidate]) -> Estimate2D:
        rounds.append([float(c.box[0]) for c in chosen])
        n = len(chosen)
        joints = torch.from_numpy(np.stack([person + (c.box[0] - 10.0) for c in chosen])).float()
        maps, zeros, ones = torch.zeros(n, NUM_JOINTS, 1, 1), torch.zeros(n), torch.ones(n)
        affine = torch.zeros(n, 2, 3)
        return Estimate2D(joints, maps[..., 0, 0], zeros, maps, affine, ones, ones)

    def evidence(estimate, candidates) -> torch.Tensor:
        psm = torch.full((len(candidates),), -200.0, dtype=torch.float64)  # a person each
        root = torch.tensor([c.proposal_score for c in candidates], dtype=torch.float64)
        return torch.stack([psm, torch.zeros_like(psm), root], -1)

    finder = PeopleFinder(SimpleNamespace(), SearchParams(), SCORE)  # type: ignore[arg-type]
    finder.evidence = evidence  # type: ignore[method-assign]
    inputs = [ImageInput(np.zeros((480, 640, 3), np.uint8), people="all", min_score=0.5)]
    candidates = [
        proposal(0.0, 300.0, False),
        proposal(10.0, 90.0, True),
        proposal(300.0, 90.0, True),
    ]
    posed, estimate, answer = finder.pose_and_answer(inputs, candidates, pose_2d)
    assert rounds == [[10.0], [310.0]]
    assert [float(c.box[0]) for c in posed] == [10.0, 310.0]
    assert answer.rows.tolist() == [0, 1] and estimate.joints_2d[1, 0, 0] == 310.0


def _candidates(monkeypatch, found: Proposals, image: np.ndarray, people: str = "all"):
    """PeopleFinder.find of one image without a box whose search finds `found`."""
    monkeypatch.setattr("ds3d.people.finder.propose", lambda *args: [found])
    estimator = SimpleNamespace(params=EstimatorParams())
    finder = PeopleFinder(estimator, SearchParams(), SCORE)  # type: ignore[arg-type]
    return finder.find([ImageInput(image, people=people)])
