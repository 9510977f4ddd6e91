"""What ds3d.Pipeline answers: the people of a batch of images (PipelineResult, batched tensors)
and one person (Person, plain arrays), the one definition that `ds3d predict`'s files and the
service's answers are written from."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ds3d.skeleton import NUM_JOINTS


@dataclass(frozen=True)
class Person:
    """One person in an image, as answered (the fields of PipelineResult, of one row).

    box: (4,) float32 x0, y0, x1, y1 px, the box of its joints. score: P(a person) in [0, 1].
    person_found: the score at least min_score, or a box was given. joints_2d: (14, 2) float32
    px, the refined pose (a joint the photo cuts off lies past its edges, as the box then);
    joints_2d_initial: (14, 2), the 2D stage's. joints_3d: (14, 3) float32
    mm, camera-oriented, root at the hip midpoint. root_position: (3,) float32 mm, the hip
    midpoint in camera coordinates (NaN where no camera was known), placed with focal length
    focal_px, the camera's or, when focal_assumed, an assumed one. confidence: (14,) float32 in
    [0, 1], P(the joint lies within PCK@0.2 of the truth) (ds3d.confidence).
    facing_camera: P(faces the camera); below 0.5 its left and right were swapped. joint_set:
    the chosen set. psm_energy: (T,) float32, after each iteration.
    """

    box: np.ndarray
    score: float
    person_found: bool
    joints_2d: np.ndarray
    joints_2d_initial: np.ndarray
    joints_3d: np.ndarray
    root_position: np.ndarray
    focal_px: float
    focal_assumed: bool
    confidence: np.ndarray
    facing_camera: float
    joint_set: str
    psm_energy: np.ndarray
    track_id: int | None = None  # in a video, the person's track (ds3d.people.tracking.Tracker)

    @property
    def joints_3d_camera(self) -> np.ndarray:
        """(14, 3) float32 mm, the joints in camera coordinates: joints_3d + root_position."""
        return self.joints_3d + self.root_position

    def to_json(self) -> dict:
        """JSON-ready: every field, arrays as lists, the joints in camera coordinates and the
        number of iterations run."""
        out = {
            f.name: value.tolist() if isinstance(value, np.ndarray) else value
            for f in dataclasses.fields(self)
            for value in [getattr(self, f.name)]
        }
        extra = {"joints_3d_camera": self.joints_3d_camera.tolist()}
        return out | extra | {"iterations": len(self.psm_energy)}


@dataclass
class PipelineResult:
    """Poses of N people, found in B images (one per image with people="best": N = B).

    image_index: (N,) int64, the image (of the B given) each person is in; people of one image
        are together, best first.
    box: (N, 4) float32 x0, y0, x1, y1 px, the box of the person's joints (ds3d.boxes).
    score: (N,) float32 in [0, 1], the probability that it is a person
        (ds3d.people.score).
    score_evidence: (N, 3) float32, what the score weighs (ds3d.people.score.person_evidence):
        the 2D stage's PSM score, the pose's limb stretch, the search's root score of its
        proposal (NaN where it had none).
    person_found: (N,) bool, the score at least min_score (with a box given: True, the caller
        said where the person is). With people="best" an image where nobody scores min_score
        still answers its likeliest pose, flagged False.
    joints_2d: (N, 14, 2) float32 px of the input image, the refined 2D pose x^ (final).
    joints_2d_initial: (N, 14, 2) float32 px, the 2D stage's pose x.
    joints_2d_iterations: (N, T, 14, 2) float32 px, x^ after each iteration.
    joints_3d: (N, 14, 3) float32 mm, camera-oriented (x right, y down, z away from the camera),
        root at the hip midpoint.
    root_position: (N, 3) float32 mm, the hip midpoint in the coordinates of the camera (x right,
        y down, z its depth): joints_3d + root_position are the joints there. Placed by the 3D
        fit's projection (ds3d.fit.camera.camera_translation) with the intrinsics given, or else a
        camera of focal length focal_px at the image's centre; NaN where no camera was known
        (Pipeline.lift_estimate called without one).
    focal_px: (N,) float32 px, the focal length (mean of f_x, f_y) of that camera.
    focal_assumed: (N,) bool, focal_px was assumed (ds3d.fit.camera.ASSUMED_FOV_DEG) rather than
        given (intrinsics or focal_px).
    confidence: (N, 14) float32 in [0, 1], the probability that the joint lies within PCK@0.2 of
        the truth (ds3d.confidence; with a model without joint_calibration.json, the 2D stage's
        probability at x^, which is not).
    facing_camera: (N,) float32 in [0, 1], the 2D stage's probability that the person faces the
        camera; below 0.5 its left and right were swapped (Estimate2D.facing_camera), so a
        value near 0.5 says the left/right labels are a guess.
    joint_set: N names, the chosen set s^.
    psm_energy: (N, T) float32, the negative MAP log-posterior of x^ after each iteration
        (non-increasing in t with selection "posterior", which keeps the better pose; with
        "energy" the last iteration's pose is kept).
    iterations: T, the number of iterations run.
    timings_ms: wall time of each stage for the whole batch.
    """

    joints_2d: torch.Tensor
    joints_2d_initial: torch.Tensor
    joints_2d_iterations: torch.Tensor
    joints_3d: torch.Tensor
    root_position: torch.Tensor
    focal_px: torch.Tensor
    focal_assumed: torch.Tensor
    confidence: torch.Tensor
    facing_camera: torch.Tensor
    joint_set: list[str]
    psm_energy: torch.Tensor
    iterations: int
    timings_ms: dict[str, float]
    image_index: torch.Tensor
    box: torch.Tensor
    score: torch.Tensor
    score_evidence: torch.Tensor
    person_found: torch.Tensor

    @classmethod
    def empty(cls, iterations: int, timings_ms: dict[str, float]) -> PipelineResult:
        """Nobody: every field with N = 0."""
        n, j = 0, NUM_JOINTS
        return cls(
            joints_2d=torch.zeros(n, j, 2),
            joints_2d_initial=torch.zeros(n, j, 2),
            joints_2d_iterations=torch.zeros(n, iterations, j, 2),
            joints_3d=torch.zeros(n, j, 3),
            root_position=torch.zeros(n, 3),
            focal_px=torch.zeros(n),
            focal_assumed=torch.zeros(n, dtype=torch.bool),
            confidence=torch.zeros(n, j),
            facing_camera=torch.zeros(n),
            joint_set=[],
            psm_energy=torch.zeros(n, iterations),
            iterations=iterations,
            timings_ms=timings_ms,
            image_index=torch.zeros(n, dtype=torch.long),
            box=torch.zeros(n, 4),
            score=torch.zeros(n),
            score_evidence=torch.zeros(n, 3),
            person_found=torch.zeros(n, dtype=torch.bool),
        )

    @classmethod
    def concat(cls, parts: Sequence[PipelineResult], offsets: Sequence[int]) -> PipelineResult:
        """One result of parts' people one after the other, offsets[k] added to part k's
        image_index (a batch split by image into consecutive parts: the index of each part's
        first image). Each stage's timings_ms are summed over the parts."""
        fields: dict = {}
        for f in dataclasses.fields(cls):
            values = [getattr(part, f.name) for part in parts]
            if f.name == "image_index":
                values = [v + int(o) for v, o in zip(values, offsets, strict=True)]
            if isinstance(values[0], torch.Tensor):
                fields[f.name] = torch.cat(values)
            elif isinstance(values[0], list):
                fields[f.name] = [x for v in values for x in v]
            elif f.name == "timings_ms":
                stages = {k: None for v in values for k in v}
                fields[f.name] = {k: sum(v.get(k, 0.0) for v in values) for k in stages}
            else:
                fields[f.name] = values[0]
        return cls(**fields)

    @classmethod
    def gather(cls, parts: Sequence[tuple[torch.Tensor, PipelineResult]]) -> PipelineResult:
        """One result of people lifted in parts: (rows (n_k,) int64, the result of those n_k
        people), the rows of all parts together 0..N-1. Timings as concat."""
        result = cls.concat([part for _, part in parts], [0] * len(parts))
        order = torch.cat([rows for rows, _ in parts]).argsort()
        return result.rows(order)

    def rows(self, index: torch.Tensor) -> PipelineResult:
        """The people `index` (K,) int64, in that order."""
        fields: dict = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, torch.Tensor):
                fields[f.name] = value[index]
            elif isinstance(value, list):
                fields[f.name] = [value[i] for i in index.tolist()]
            else:
                fields[f.name] = value
        return PipelineResult(**fields)

    def person(self, i: int) -> Person:
        """Person i (of the N)."""
        return Person(
            box=self.box[i].numpy(),
            score=float(self.score[i]),
            person_found=bool(self.person_found[i]),
            joints_2d=self.joints_2d[i].numpy(),
            joints_2d_initial=self.joints_2d_initial[i].numpy(),
            joints_3d=self.joints_3d[i].numpy(),
            root_position=self.root_position[i].numpy(),
            focal_px=float(self.focal_px[i]),
            focal_assumed=bool(self.focal_assumed[i]),
            confidence=self.confidence[i].numpy(),
            facing_camera=float(self.facing_camera[i]),
            joint_set=self.joint_set[i],
            psm_energy=self.psm_energy[i].numpy(),
        )

    def people(self, image: int) -> list[Person]:
        """The people of image `image` (of those given), best first."""
        return [self.person(i) for i in torch.nonzero(self.image_index == image).view(-1).tolist()]
