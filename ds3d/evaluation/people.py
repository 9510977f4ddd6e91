"""People in photos, scored: detection recall and precision and the pose of the people found on
the canvases of ds3d.evaluation.canvases, and the person score's fit and calibration.

Scores, per person size (the person's height as a fraction of the canvas height, uncut): detection
recall and precision at IoU >= 0.5 between person boxes (ds3d.boxes.person_boxes, for the truth
and the prediction alike, clipped to the canvas), and PCK@0.2 of the people found
(ds3d.evaluation.metrics.pck); precision also for the large people alone (LARGE, and answers of
that size).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from ds3d.boxes import iou, person_boxes
from ds3d.evaluation.canvases import LARGE, SIZE_BINS, Canvas
from ds3d.evaluation.metrics import expected_calibration_error, pck, reliability
from ds3d.inputs import MIN_SCORE
from ds3d.people.score import fit_person_score
from ds3d.pipeline import Pipeline
from ds3d.util.progress import progress


def match(predicted: np.ndarray, scores: np.ndarray, truth: np.ndarray, threshold: float = 0.5):
    """Greedy matching, best score first, of predicted boxes (N, 4) to true boxes (M, 4) at IoU
    >= threshold, each true box taken once. Returns (M,) int: the prediction matched to each true
    box, -1 for none."""
    found = np.full(len(truth), -1)
    if len(predicted) == 0 or len(truth) == 0:
        return found
    overlap = iou(predicted, truth)
    for p in np.argsort(-np.asarray(scores), kind="stable"):
        free = np.where(found < 0, overlap[p], -1.0)
        best = int(free.argmax())
        if free[best] >= threshold:
            found[best] = p
    return found


def score(canvases: list[Canvas], predictions: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    """Recall and PCK@0.2 per size bin and overall, precision overall; recall and precision
    of the large people (LARGE: those people, and the answers matched to them or of that size
    unmatched); the answers on canvases without people. predictions: per canvas, the predicted
    poses (N, 14, 2) px and their scores (N,), higher = surer."""
    rows = []  # (size fraction, matched?, predicted joints or None, true joints, located)
    false_positives = 0
    total_predictions = 0
    large_right = large_wrong = phantoms = 0
    for canvas, (poses, scores) in zip(canvases, predictions, strict=True):
        poses = np.asarray(poses, np.float64).reshape(-1, 14, 2)
        found = match(canvas.within(person_boxes(poses)), scores, canvas.boxes())
        total_predictions += len(poses)
        false_positives += len(poses) - int((found >= 0).sum())
        if len(canvas.heights) == 0:
            phantoms += len(poses)
        answered_large = np.ptp(poses, axis=1).max(-1) >= LARGE * canvas.image.shape[0]
        person_of = np.full(len(poses), -1)
        person_of[found[found >= 0]] = np.nonzero(found >= 0)[0]
        for p, person in enumerate(person_of):
            if person >= 0:
                large_right += int(canvas.heights[person] >= LARGE)
            else:
                large_wrong += int(answered_large[p])
        for person, p in enumerate(found):
            rows.append(
                (
                    canvas.heights[person],
                    p >= 0,
                    poses[p] if p >= 0 else None,
                    canvas.joints[person],
                    canvas.inside()[person],
                )
            )
    report: dict = {"canvases": len(canvases), "people": len(rows), "bins": {}}

    def summary(selected) -> dict:
        matched = [r for r in selected if r[1]]
        out = {"people": len(selected), "recall": len(matched) / max(len(selected), 1)}
        if matched:
            pred = np.stack([r[2] for r in matched])
            truth = np.stack([r[3] for r in matched])
            located = np.stack([r[4] for r in matched])
            out["pck@0.2"] = float(pck(pred, truth, located).mean())
        return out

    for low, high in SIZE_BINS:
        name = f"{round(100 * low)}-{round(100 * high)}%"
        report["bins"][name] = summary([r for r in rows if low <= r[0] < high or r[0] == high])
    report["all"] = summary(rows)
    report["all"]["precision"] = (total_predictions - false_positives) / max(total_predictions, 1)
    large = summary([r for r in rows if r[0] >= LARGE])
    report["large"] = {
        "people": large["people"],
        "recall": large["recall"],
        "precision": large_right / max(large_right + large_wrong, 1),
    }
    report["empty_canvases"] = sum(len(c.heights) == 0 for c in canvases)
    report["answers_on_empty_canvases"] = phantoms
    return report


@dataclass
class Candidates:
    """Every person a pipeline answers on one canvas at min_score 0: poses (N, 14, 2) px as
    answered, scores (N,) their person scores, evidence (N, 3) what the scores weigh
    (ds3d.people.score.person_evidence)."""

    poses: np.ndarray
    scores: np.ndarray
    evidence: np.ndarray

    def above(self, min_score: float) -> tuple[np.ndarray, np.ndarray]:
        """The poses and scores answered at min_score."""
        kept = self.scores >= min_score
        return self.poses[kept], self.scores[kept]


def candidates_of(pipeline: Pipeline, canvases: list[Canvas], batch: int) -> list[Candidates]:
    """Per canvas, every person the pipeline answers at min_score 0, `batch` canvases at a
    time."""
    out = []
    with progress(total=len(canvases), desc="people", unit="img") as bar:
        for first in range(0, len(canvases), batch):
            part = canvases[first : first + batch]
            result = pipeline.estimate([c.image for c in part], people="all", min_score=0.0)
            for i in range(len(part)):
                own = result.rows(torch.nonzero(result.image_index == i).view(-1))
                fields = (own.joints_2d, own.score, own.score_evidence)
                out.append(Candidates(*(f.double().numpy() for f in fields)))
            bar.update(len(part))
    return out


def calibration(
    canvases: list[Canvas], candidates: list[Candidates], root_reference: float
) -> dict:
    """The PersonScore that these candidates fit (ds3d.people.score.fit_person_score: whether
    each matches a person, `match`, against its evidence; root_reference, the search's proposal
    floor), and how well their scores as answered say how often a candidate is a person: the
    expected calibration error and reliability bins (ds3d.evaluation.metrics). Fit on training
    canvases only."""
    evidence, matched, answered = [], [], []
    for canvas, found in zip(canvases, candidates, strict=True):
        boxes = canvas.within(person_boxes(found.poses))
        matches = match(boxes, found.scores, canvas.boxes()) if len(found.poses) else []
        label = np.zeros(len(found.poses), bool)
        label[[p for p in matches if p >= 0]] = True
        evidence.append(found.evidence.reshape(-1, 3))
        matched.append(label)
        answered.append(found.scores)
    person = np.concatenate(matched)
    said = torch.from_numpy(np.concatenate(answered))
    fitted = fit_person_score(np.concatenate(evidence), person, root_reference)
    return {
        "candidates": len(person),
        "people": int(person.sum()),
        "person_score": dataclasses.asdict(fitted),
        "ece": round(expected_calibration_error(said, torch.from_numpy(person)), 4),
        "reliability": reliability(said, torch.from_numpy(person)),
    }


def people_report(
    pipeline: Pipeline, canvases: list[Canvas], candidates: list[Candidates], batch: int
) -> dict:
    """The protocol's figures of a pipeline on canvases, its answers there at min_score 0 given
    (candidates_of): the scores at the default min_score and at others, the person score's
    calibration, and the images/s of a second pass as a user meets it (people="all" at the
    default min_score, which lifts only the people answered)."""
    with progress(total=len(canvases), desc="people, timed", unit="img") as bar:
        start = time.perf_counter()
        for first in range(0, len(canvases), batch):
            part = canvases[first : first + batch]
            pipeline.estimate([c.image for c in part], people="all")
            bar.update(len(part))
        seconds = time.perf_counter() - start
    floor = pipeline.config.search.proposal_floor
    report = {
        "min_score": MIN_SCORE,
        "images_per_s": round(len(canvases) / seconds, 2),
        **score(canvases, [c.above(MIN_SCORE) for c in candidates]),
        "calibration": calibration(canvases, candidates, floor),
        "by_min_score": {},
    }
    for threshold in (0.1, 0.2, 0.3, 0.5, 0.7):
        figures = score(canvases, [c.above(threshold) for c in candidates])
        report["by_min_score"][str(threshold)] = {
            "recall": {name: round(b["recall"], 4) for name, b in figures["bins"].items()},
            "precision": round(figures["all"]["precision"], 4),
            "large": {name: round(v, 4) for name, v in figures["large"].items()},
            "answers_on_empty_canvases": figures["answers_on_empty_canvases"],
        }
    return report
