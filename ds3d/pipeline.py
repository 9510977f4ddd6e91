"""ds3d.Pipeline: images in, 2D and 3D poses out, by the dual-source approach end to end.

find      the crops of each image: a box given, or the people search's proposals
          (ds3d.people.finder, ds3d.people.search)
2D        unaries + PSM of every crop (ds3d.image2d.estimator)
answer    who is answered: the best person of each image, or every one found, by the person
          score (ds3d.people.finder, ds3d.people.score); only they go on
lift      the paper's iterative approach: retrieval weighted by the image, the refinement of
          the 2D pose, the joint set, the 3D fit (ds3d.iterative), each person placed in
          the camera's coordinates
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import torch

from ds3d.boxes import person_boxes
from ds3d.confidence import FILE_NAME as CALIBRATION_FILE
from ds3d.confidence import JointCalibration
from ds3d.fit.camera import pinhole
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.result import LOG_EPS, Estimate2D, gather_rows
from ds3d.inputs import MIN_SCORE, ImageInput, image_inputs
from ds3d.iterative import SELECTIONS, lift_with_image
from ds3d.lifter import Lifter, LifterConfig
from ds3d.people.finder import Candidate, PeopleFinder
from ds3d.people.score import PersonScore
from ds3d.people.search import SearchParams
from ds3d.refine import RefineParams
from ds3d.result import PipelineResult
from ds3d.util.groups import group_rows
from ds3d.util.paths import MODELS_DIR

STEPS_2D = ("features", "traversal", "jointnet", "psm")  # the steps of Estimate2D.timings, s


@dataclass(frozen=True)
class PipelineConfig:
    """Parameters of the image-driven steps (the 3D stage's are in LifterConfig): the number of
    iterations (the paper's 2; with the bundled 2D stage the second adds nothing measurable:
    docs/RESULTS.md), how the joint set is chosen: "posterior" (eqt:best_segments_pose) or
    "energy" (eq:energyS; the refined pose is then the chosen set's PSM MAP), the refinement's
    parameters, and how people are found in images given without a box."""

    iterations: int = 1
    selection: str = "posterior"
    refine: RefineParams = field(default_factory=RefineParams)
    search: SearchParams = field(default_factory=SearchParams)

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.selection not in SELECTIONS:
            raise ValueError(f"selection must be one of {SELECTIONS}, got {self.selection!r}")


class Pipeline:
    """Load once, estimate many: `Pipeline.load().estimate(images)`; `run` takes images already
    checked (ds3d.inputs.image_input), as the service and the runners make them."""

    def __init__(
        self,
        estimator: PoseEstimator2D,
        lifter: Lifter,
        config: PipelineConfig = PipelineConfig(),
        joint_calibration: JointCalibration | None = None,
        person_score: PersonScore | None = None,
    ):
        self.estimator = estimator
        self.lifter = lifter
        self.config = config
        self.joint_calibration = joint_calibration  # None: the raw confidences
        self.person_score = person_score  # None: people cannot be scored (PeopleFinder.score)

    @classmethod
    def load(
        cls,
        model_dir: str | Path | None = None,
        device: str = "cpu",
        config: PipelineConfig = PipelineConfig(),
        lifter_config: LifterConfig | None = None,
        database: str = "posedb",
        image2d: str = "image2d",
    ) -> Pipeline:
        """The models of `model_dir` (default models/): the 2D stage in `image2d`, with the
        numbers fitted to it beside it (joint_calibration.json, ds3d.confidence;
        person_score.json, ds3d.people.score), the pose database in `database`; both stages on
        `device` (PoseEstimator2D.to, Lifter). Raises DataFormatError when either is missing
        or malformed."""
        directory = Path(model_dir) if model_dir is not None else MODELS_DIR
        estimator = PoseEstimator2D.load(directory / image2d, device)
        lifter_config = LifterConfig() if lifter_config is None else lifter_config
        lifter = Lifter.load(directory, device=device, config=lifter_config, database=database)
        calibration_file = directory / image2d / CALIBRATION_FILE
        calibration = JointCalibration.load(calibration_file) if calibration_file.exists() else None
        score = PersonScore.load(directory / image2d)
        return cls(estimator, lifter, config, calibration, score)

    @property
    def model_id(self) -> str:
        return self.lifter.model_id

    @property
    def finder(self) -> PeopleFinder:
        """The people finder of this model and config.search."""
        return PeopleFinder(self.estimator, self.config.search, self.person_score)

    def estimate(
        self,
        images,
        bboxes=None,
        intrinsics=None,
        iterations: int | None = None,
        people: str | Sequence[str] = "best",
        min_score: float | Sequence[float] = MIN_SCORE,
        focal_px: float | Sequence[float | None] | None = None,
    ) -> PipelineResult:
        """2D and 3D poses of the people in B images.

        images: B arrays (H_i, W_i, 3) uint8 RGB (none: an empty result); bboxes: None or B
        entries, each None or a person box (x0, y0, x1, y1) px: an image with a box is estimated
        in it, one without is searched for people (ds3d.people); intrinsics: None (an image
        without: weak perspective), one (3, 3) pinhole matrix for all, or B entries each None or
        one; iterations: overrides config.iterations; focal_px: without intrinsics, the focal
        length of the camera that took the images, for every image or one per image, which
        places the people in its coordinates (PipelineResult.root_position; None: an assumed
        one, ds3d.fit.camera.ASSUMED_FOV_DEG). people: "best", one person per image
        (PipelineResult.person_found says whether anybody scored min_score), or "all", every
        person scoring at least min_score (none for an image without people); people and
        min_score are for every image or one per image. Only the people answered are lifted, so
        an image's answer is the same whichever other images, asking whatever, share its call
        (up to the 3D stage's rounding, which depends on how many people are lifted together).
        Raises InvalidImage, InvalidBox, InvalidPose or ValueError (ds3d.inputs.image_input).
        """
        checked = image_inputs(images, bboxes, intrinsics, focal_px, people, min_score)
        return self.run(checked, iterations)

    def run(self, inputs: Sequence[ImageInput], iterations: int | None = None) -> PipelineResult:
        """estimate() of images already checked, each with its own options (ImageInput)."""
        inputs = list(inputs)
        if not inputs:
            return PipelineResult.empty(iterations or self.config.iterations, {"total": 0.0})
        t_start = time.perf_counter()
        finder = self.finder
        search_steps: dict[str, float] = {}
        candidates = finder.find(inputs, search_steps)
        search_ms = 1000 * (time.perf_counter() - t_start)
        images = [item.image for item in inputs]
        candidates, estimate, answer = finder.pose_and_answer(
            inputs, candidates, partial(self.estimate_2d, images)
        )
        image_index = torch.tensor([c.image for c in candidates], dtype=torch.long)[answer.rows]
        people = [inputs[i] for i in image_index.tolist()]
        parts = []  # the lifter takes intrinsics for all of its batch or for none
        groups = group_rows(item.intrinsics is not None for item in people).values()
        for k, rows in enumerate(groups or [[]]):
            answered = answer.rows[rows]
            part = estimate.rows(answered)
            part.timings = part.timings if k == 0 else {}  # the 2D stage's, counted once
            intrinsics = _intrinsics([people[i] for i in rows])
            camera = intrinsics if intrinsics is not None else _cameras([people[i] for i in rows])
            people_answered = answer.score[answered], answer.evidence[answered]
            lifted = self.lift_estimate(part, intrinsics, iterations, camera, people_answered)
            lifted.person_found = answer.found[answered]
            parts.append((torch.tensor(rows, dtype=torch.long), lifted))
        result = PipelineResult.gather(parts)
        result.image_index = image_index
        result.focal_assumed = torch.tensor(
            [item.intrinsics is None and item.focal_px is None for item in people]
        )
        result.timings_ms = {
            "search": round(search_ms, 3),
            # of which the joint network's passes over the levels (CPU ms summed over threads)
            "search_jointnet": round(1000 * search_steps.get("jointnet", 0.0), 3),
            **result.timings_ms,
        }
        result.timings_ms["total"] = round(1000 * (time.perf_counter() - t_start), 3)
        return result

    def estimate_2d(self, images: list[np.ndarray], candidates: list[Candidate]) -> Estimate2D:
        """The 2D stage of every candidate, in the candidates' order: those of known scale at
        that scale alone, the others over the pyramid."""
        parts = []
        for scale_known in (False, True):
            rows = [k for k, c in enumerate(candidates) if c.scale_known == scale_known]
            if rows:
                part = self.estimator.estimate(
                    [images[candidates[k].image] for k in rows],
                    [candidates[k].box for k in rows],
                    scales=[1.0] if scale_known else None,
                    views=[candidates[k].views for k in rows],
                )
                parts.append((torch.tensor(rows), part))
        return parts[0][1] if len(parts) == 1 else gather_rows(parts, len(candidates))

    @torch.inference_mode()
    def lift_estimate(
        self,
        estimate: Estimate2D,
        intrinsics=None,
        iterations: int | None = None,
        camera=None,
        people: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> PipelineResult:
        """Everything after the 2D stage, on its result for B people: lets a caller run several
        configurations on one 2D estimate. intrinsics: optional (B, 3, 3), the camera the 2D
        poses were taken by; camera: optional (B, 3, 3), the intrinsics of the camera in whose
        coordinates to place the people (run passes those given, or a camera of each image's
        size); without, root_position is NaN. people: their person scores (B,) and what the
        scores weigh (B, 3), as PeopleFinder.answer found them (None: NaN, for poses that were
        not answered as people)."""
        iterations = iterations or self.config.iterations
        timings = {f"2d_{step}": 1000 * estimate.timings.get(step, 0.0) for step in STEPS_2D}
        if len(estimate.joints_2d) == 0:
            return PipelineResult.empty(iterations, timings)
        t_start = time.perf_counter()
        cfg = self.config
        lifted = lift_with_image(
            self.lifter,
            self.estimator.params,
            estimate,
            iterations,
            cfg.selection,
            cfg.refine,
            None if intrinsics is None else torch.as_tensor(intrinsics, dtype=torch.float32),
            camera,
            timings,
        )
        x = lifted.joints_2d
        on_device = dataclasses.replace(
            estimate,
            unaries=estimate.unaries.to(x.device),
            map_to_image=estimate.map_to_image.to(x.device),
        )
        probability = (on_device.sample_unaries(x[:, None]).exp()[:, 0] - LOG_EPS).clamp(0.0, 1.0)
        if self.joint_calibration is not None:
            probability = self.joint_calibration(probability)
        timings["total"] = 1000 * (time.perf_counter() - t_start + estimate.timings.get("total", 0))
        joints_2d = x.cpu()
        score, evidence = people or (
            torch.full((len(joints_2d),), torch.nan),
            torch.full((len(joints_2d), 3), torch.nan),
        )
        focal = torch.full((len(joints_2d),), torch.nan)
        if camera is not None:
            focal = (camera[:, 0, 0] + camera[:, 1, 1]).float().cpu() / 2
        return PipelineResult(
            joints_2d=joints_2d,
            joints_2d_initial=lifted.joints_2d_initial.cpu(),
            joints_2d_iterations=lifted.joints_2d_iterations.cpu(),
            joints_3d=lifted.joints_3d.cpu(),
            root_position=lifted.root_position.cpu(),
            focal_px=focal,
            focal_assumed=torch.zeros(len(joints_2d), dtype=torch.bool),
            confidence=probability.cpu(),
            facing_camera=estimate.facing_camera.cpu(),
            joint_set=self.lifter.set_names(lifted.joint_set),
            psm_energy=lifted.psm_energy.cpu(),
            iterations=iterations,
            timings_ms={name: round(ms, 3) for name, ms in timings.items()},
            image_index=torch.arange(len(joints_2d)),
            box=torch.from_numpy(person_boxes(joints_2d.numpy())).float(),
            score=score.float(),
            score_evidence=evidence.float(),
            person_found=torch.ones(len(joints_2d), dtype=torch.bool),
        )


def _intrinsics(people: list[ImageInput]) -> torch.Tensor | None:
    """(P, 3, 3) the intrinsics of P people's images, which all have them or none (None)."""
    given = [item.intrinsics for item in people if item.intrinsics is not None]
    return torch.from_numpy(np.stack(given)) if given else None


def _cameras(people: list[ImageInput]) -> torch.Tensor:
    """(P, 3, 3) a pinhole camera of each person's image size and focal_px (assumed: None)."""
    cameras = [pinhole(p.image.shape[1], p.image.shape[0], p.focal_px) for p in people]
    return torch.stack(cameras) if cameras else torch.zeros(0, 3, 3)
