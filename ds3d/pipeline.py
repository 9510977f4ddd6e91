"""ds3d.Pipeline: images in, 2D and 3D poses out, by the dual-source approach end to end.

    search           without a box, where the people are (ds3d.image2d.search): each
                     proposal's box, and the whole image's where it proposes at most one
                     person, goes through the 2D stage as its own crop
    2D stage         unaries + PSM on a 6-scale pyramid -> x (ds3d.image2d.estimator)
    who is answered  per image, non-maximum suppression of the crops' poses by score
                     (ds3d.boxes), the best ("best") or those scoring min_score ("all"),
                     then the weak proposals' scoring it apart from them; only they go on
    per iteration t = 1..T (the query is x, then the refined x^ of the previous iteration):
      retrieval      K neighbours per joint set                         (ds3d.lifter)
      projection fit M_s per set (eq:projerr1), warm-started from t - 1 (ds3d.lifter)
      weighting      eq:wt: the unaries summed at each neighbour's projected joints; keep the
                     K_w best and min-max normalise them (eq:wtn)
      refinement     eqt:best_segments_pose: one PSM per (image, set) with the image's
                     unaries and binaries (c = 5 mixtures) fit to the set's weighted
                     projected neighbours; (x^, s^) = the best MAP over the sets (ds3d.refine)
    3D fit           eq:energyMin2 once, on the chosen set, with E_p measured against x^

The unaries are computed once; later iterations reuse them.

Iterations never make the refinement worse by its own measure: the pair (x^, s^) is the argmax
of the posterior over the sets of every iteration run so far, so the PSM energy (the negative
MAP log-posterior) of the answer after iteration t + 1 is at most that after t. Comparing the
models of two iterations is the same comparison eqt:best_segments_pose makes between the models
of two joint sets (each a PSM with the same unaries and its own data-driven binaries).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ds3d.boxes import checked_box, iou, joints_on_bones, person_boxes, shared_joints, suppress
from ds3d.confidence import FILE_NAME as CALIBRATION_FILE
from ds3d.confidence import JointCalibration
from ds3d.fit.camera import pinhole, project
from ds3d.fit.energy import projection_energy
from ds3d.image2d.crops import crop_region
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.jointnet import ScaledLogits
from ds3d.image2d.result import LOG_EPS, Estimate2D, gather_rows
from ds3d.image2d.search import Proposals, SearchParams, person_evidence, person_probability
from ds3d.inputs import focal_length
from ds3d.lifter import Lifter, LifterConfig, Problems, Query
from ds3d.refine import RefineParams, refine
from ds3d.result import PipelineResult
from ds3d.skeleton import NUM_JOINTS
from ds3d.util.paths import MODELS_DIR
from ds3d.util.timing import stage_timer

STEPS_2D = ("features", "traversal", "jointnet", "psm")  # the steps of Estimate2D.timings, s
PEOPLE = ("best", "all")  # Pipeline.estimate: the best person of each image, or every one
# Pipeline.estimate's default: people less likely than this are not answered. The score is a
# calibrated probability (expected calibration error 0.016 on LSP train's held-out canvases,
# `ds3d eval people --split train --start 700`, 0.034 on their harder kind, `--empty 0.2 --cut
# 0.3`): answered where more likely a person than not. There 96.6 % of the answers were people,
# at 94.1 % recall (at 0.2, 95.2 % of the answers were people).
MIN_SCORE = 0.5


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
        if self.selection not in ("posterior", "energy"):
            raise ValueError(f"selection must be 'posterior' or 'energy', got {self.selection!r}")


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


def neighbour_scores(estimate: Estimate2D, projected: torch.Tensor) -> torch.Tensor:
    """eq:wt: the unaries summed at the projected joints of each neighbour.
    projected: (B, S, K, 14, 2) px of the input image. Returns (B, S, K), higher = better."""
    b, s, k = projected.shape[:3]
    return estimate.sample_unaries(projected.reshape(b, s * k, NUM_JOINTS, 2)).sum(-1).view(b, s, k)


class Pipeline:
    """Load once, estimate many: `Pipeline.load().estimate(images)`. Its steps, each a method:
    candidates (the people search), estimate_2d (the 2D stage), answered (who is answered),
    lift_estimate (the 3D stage with the refinement)."""

    def __init__(
        self,
        estimator: PoseEstimator2D,
        lifter: Lifter,
        config: PipelineConfig = PipelineConfig(),
        joint_calibration: JointCalibration | None = None,
    ):
        self.estimator = estimator
        self.lifter = lifter
        self.config = config
        self.joint_calibration = joint_calibration  # None: the raw confidences

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
        """The models of `model_dir` (default models/): the 2D stage in `image2d` (with its
        joint_calibration.json where it has one, ds3d.confidence), the pose database in
        `database`; both stages on `device` (PoseEstimator2D.to, Lifter). Raises DataFormatError
        when either is missing or malformed."""
        directory = Path(model_dir) if model_dir is not None else MODELS_DIR
        estimator = PoseEstimator2D.load(directory / image2d, device)
        lifter_config = LifterConfig() if lifter_config is None else lifter_config
        lifter = Lifter.load(directory, device=device, config=lifter_config, database=database)
        calibration_file = directory / image2d / CALIBRATION_FILE
        calibration = JointCalibration.load(calibration_file) if calibration_file.exists() else None
        return cls(estimator, lifter, config, calibration)

    @property
    def model_id(self) -> str:
        return self.lifter.model_id

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
        in it, one without is searched for people (ds3d.image2d.search); intrinsics: None (weak
        perspective) or (B, 3, 3) / (3, 3) pinhole matrices; iterations: overrides
        config.iterations; focal_px: without intrinsics, the focal length of the camera that
        took the images, for every image or one per image, which places the people in its
        coordinates (PipelineResult.root_position; None: an assumed one,
        ds3d.fit.camera.ASSUMED_FOV_DEG). people: "best", one person per image
        (PipelineResult.person_found says whether anybody scored min_score), or "all", every
        person scoring at least min_score (none for an image without people); people and
        min_score are for every image or one per image. Only the people answered are lifted, so
        an image's answer is the same whichever other images, asking whatever, share its call
        (up to the 3D stage's rounding, which depends on how many people are lifted together).
        Raises InvalidImage, InvalidBox (ds3d.boxes.checked_box), InvalidPose (bad intrinsics or
        focal_px) or ValueError (bad people or min_score).
        """
        images = list(images)
        focal = [
            None if f is None else focal_length(f)
            for f in _per_image(focal_px, len(images), "focal_px")
        ]
        people, min_score = _people_asked(people, min_score, len(images))
        boxes = _checked_boxes(images, bboxes)
        if not images:
            return PipelineResult.empty(iterations or self.config.iterations, {"total": 0.0})
        t_start = time.perf_counter()
        candidates = self.candidates(images, boxes, people)
        search_ms = 1000 * (time.perf_counter() - t_start)
        estimate = self.estimate_2d(images, candidates)
        evidence = self.person_evidence(estimate, candidates)
        answered, found = self.answered(candidates, estimate, evidence, people, min_score)
        image_index = torch.tensor([c.image for c in candidates], dtype=torch.long)[answered]
        # the camera that places the people: the intrinsics given, or one per image of its size
        if intrinsics is not None:
            intrinsics = torch.as_tensor(np.asarray(intrinsics, np.float32))
            intrinsics = intrinsics[image_index] if intrinsics.ndim == 3 else intrinsics
            camera = intrinsics.expand(len(image_index), 3, 3)
        else:
            sizes = [(i, *images[i].shape[1::-1]) for i in image_index.tolist()]
            camera = torch.stack([pinhole(w, h, focal[i]) for i, w, h in sizes]) if sizes else None
        result = self.lift_estimate(
            estimate.rows(answered), intrinsics, iterations, camera, evidence[answered]
        )
        assumed = [intrinsics is None and focal[i] is None for i in image_index.tolist()]
        result.focal_assumed = torch.tensor(assumed, dtype=torch.bool)
        result.image_index = image_index
        result.person_found = found[answered]
        result.timings_ms = {"search": round(search_ms, 3), **result.timings_ms}
        result.timings_ms["total"] = round(1000 * (time.perf_counter() - t_start), 3)
        return result

    def candidates(
        self, images: list[np.ndarray], boxes: list, people: Sequence[str] | None = None
    ) -> list[Candidate]:
        """The crops of B images: each given box, whose scale the 2D stage chooses; for an
        image without one, its people search's proposals (ds3d.image2d.search), whose scale
        the search has found, and, where it proposes at most one person, the whole image as
        one more box, which finds people the image's edge cuts, unless the proposal's crop
        already holds most of the image (SearchParams.whole_image_cover). people: per image,
        as Pipeline.estimate (None: all "all"); an image asked for its best person has its
        best proposal alone estimated.
        (Estimating the others too and answering the best by the 2D stage's score gave 79.76
        against 79.93 % PCK held out, ds3d eval lsp-pipeline --searched, at twice the 2D
        stage's time on every image with a second proposal.)"""
        searched = [i for i, box in enumerate(boxes) if box is None]
        proposals = self.estimator.propose([images[i] for i in searched], self.config.search)
        out = [Candidate(i, box, True, False) for i, box in enumerate(boxes) if box is not None]
        for i, found in zip(searched, proposals, strict=True):
            whole = np.array([0, 0, images[i].shape[1], images[i].shape[0]], np.float32)
            proposed = self._proposals_on(i, found)
            strong = [c.box for c in proposed if not c.weak]
            # The whole image is one person's crop: where the search found several people,
            # its one pose would join them.
            alone = len(strong) <= 1
            if people is not None and people[i] == "best":
                proposed = proposed[:1]
            out += proposed
            if alone and not any(self._covers(box, images[i]) for box in strong):
                out.append(Candidate(i, whole, False, False, found.levels))
        return out

    def _proposals_on(self, image: int, proposals: Proposals) -> list[Candidate]:
        """The candidates of image `image`'s proposals that go on to the 2D stage, best
        first, each the box of the proposal's joints (so that the crop's base scale is the
        proposal's): the best max_people of those scoring proposal_floor, and always the best;
        then, weak, the best weak_people of the others scoring weak_floor. Only proposals whose
        box has an area: a pose whose joints all share one column or row (a PSM collapsed
        against the edge of a level's maps) is nobody, and a crop needs an area."""
        search, scores = self.config.search, proposals.scores
        boxes = np.concatenate([proposals.poses.min(1), proposals.poses.max(1)], 1)
        area = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        strong = scores >= search.proposal_floor
        strong[:1] = True
        weak = ~strong & (scores >= search.weak_floor)
        chosen = [
            (k, kind)
            for kind, among, most in (
                (False, strong, search.max_people),
                (True, weak, search.weak_people),
            )
            for k in np.nonzero(among & area)[0][:most]
        ]
        return [
            Candidate(image, boxes[k], False, True, (), float(scores[k]), kind)
            for k, kind in chosen
        ]

    def _covers(self, box: np.ndarray, image: np.ndarray) -> bool:
        """Whether the crop around a person box (crops.crop_region) holds at least
        SearchParams.whole_image_cover of the image's area."""
        height, width = image.shape[:2]
        (x0, y0, x1, y1), _ = crop_region(box, width, height, self.estimator.params)
        inside = (min(x1, width) - max(x0, 0)) * (min(y1, height) - max(y0, 0))
        return inside >= self.config.search.whole_image_cover * width * height

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
        estimate = parts[0][1] if len(parts) == 1 else gather_rows(parts, len(candidates))
        estimate.timings = {k: sum(part.timings.get(k, 0.0) for _, part in parts) for k in STEPS_2D}
        return estimate

    def answered(
        self,
        candidates: list[Candidate],
        estimate: Estimate2D,
        evidence: torch.Tensor,
        people: list[str],
        min_score: list[float],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Who is answered, settled on the 2D stage's poses so that only they are lifted: per
        image, after non-maximum suppression of its candidates by score (their pose boxes
        overlapping by SearchParams.overlap, their poses sharing same_person_joints joints, or
        one's on_bones_joints joints lying on the other's bones: one person found twice), the
        best one (people[image] "best") or those found ("all"); then, best score first, the weak
        candidates found whose box overlaps no answered one's by more than weak_overlap (IoU):
        a weak proposal is a person the search was unsure of, answered where nobody found
        stands, not as a second reading of them. A candidate is found when its box was given
        or it scores min_score[image] (person_probability of its evidence, (C, 3)
        person_evidence). Returns the rows of `estimate` answered (N,) int64, image by image,
        best first, and found (C,) bool."""
        # on the CPU: a few numbers per candidate, settled with NumPy
        score = person_probability(evidence, self.config.search).float()
        image_index = torch.tensor([c.image for c in candidates], dtype=torch.long)
        given = torch.tensor([c.given for c in candidates])
        found = given | (score >= torch.tensor(min_score, dtype=score.dtype)[image_index])
        search = self.config.search
        poses = estimate.joints_2d.cpu().numpy()
        boxes = person_boxes(poses)
        rows = [torch.zeros(0, dtype=torch.long)]
        for image in image_index.unique().tolist():
            own = torch.nonzero(image_index == image).view(-1)
            if people[image] == "best":  # the suppression keeps the best first: it alone
                rows.append(own[score[own].argmax()].view(1))
                continue
            weak = torch.tensor([candidates[k].weak for k in own.tolist()])
            strong = own[~weak].numpy()
            shared = shared_joints(poses[strong], search.same_person_radius)
            on_bones = joints_on_bones(poses[strong], search.on_bones_radius)
            same = (shared >= search.same_person_joints) | (on_bones >= search.on_bones_joints)
            same |= same.T
            kept = strong[suppress(boxes[strong], score[strong].numpy(), search.overlap, same)]
            answered = kept[found[kept].numpy()].tolist()
            for k in own[weak][score[own[weak]].argsort(descending=True)].tolist():
                apart = not answered or iou(boxes[k], boxes[answered]).max() <= search.weak_overlap
                if found[k] and apart:
                    answered.append(k)
            answered.sort(key=lambda k: -float(score[k]))
            rows.append(torch.tensor(answered, dtype=torch.long))
        return torch.cat(rows), found

    def person_evidence(
        self, estimate: Estimate2D, candidates: list[Candidate] | None = None
    ) -> torch.Tensor:
        """(B, 3) on the CPU: what the person score of each of the 2D stage's B poses weighs
        (ds3d.image2d.search.person_evidence: its PSM score, its limbs' proportions against the
        PSM's typical ones, the root score of its candidate's proposal; None: no candidate was
        a proposal)."""
        typical = self.estimator.mixtures.typical_lengths().float().cpu()
        root = torch.full((len(estimate.score),), math.nan)
        if candidates is not None:
            root = torch.tensor([c.proposal_score for c in candidates], dtype=torch.float64)
        psm, joints = estimate.score.float().cpu(), estimate.joints_2d.float().cpu()
        return person_evidence(psm, joints, typical, root, self.config.search)

    @torch.inference_mode()
    def lift_estimate(
        self,
        estimate: Estimate2D,
        intrinsics=None,
        iterations: int | None = None,
        camera=None,
        evidence: torch.Tensor | None = None,
    ) -> PipelineResult:
        """Everything after the 2D stage, on its result for B people (arguments as estimate):
        lets a caller run several configurations on one 2D estimate. camera: optional (B, 3, 3),
        the intrinsics of the camera in whose coordinates to place the people (estimate passes
        those given, or a camera of each image's size); without, root_position is NaN.
        evidence: (B, 3) their person_evidence (None: of poses that no proposal found)."""
        cfg = self.config
        if iterations is not None:
            cfg = dataclasses.replace(cfg, iterations=iterations)
        lifter, dev = self.lifter, self.lifter.device
        t_start = time.perf_counter()
        timings = {f"2d_{step}": 1000 * estimate.timings.get(step, 0.0) for step in STEPS_2D}
        if len(estimate.joints_2d) == 0:
            return PipelineResult.empty(cfg.iterations, timings)
        est = dataclasses.replace(
            estimate, unaries=estimate.unaries.to(dev), map_to_image=estimate.map_to_image.to(dev)
        )
        # One frame for every iteration: the warm-started projections stay in its coordinates.
        first = lifter.query(est.joints_2d.to(dev), None, intrinsics)
        query = first
        best: _State | None = None  # per person, the state with the best posterior so far
        start = None  # every set's projections of the iteration before, for a warm start
        history, energies = [], []
        for _ in range(cfg.iterations):
            state, start = self._iterate(est, query, start, cfg, timings)
            # energy selection has no common measure across iterations: the last one wins
            best = state if best is None or cfg.selection == "energy" else best.merge(state)
            query = query.moved_to(best.joints_2d)
            history.append(best.joints_2d)
            energies.append(-best.score)
        assert best is not None  # cfg.iterations >= 1 (PipelineConfig)
        with stage_timer(timings, "pose_fit", dev):
            chosen = lifter.problems(query, best.joint_set)
            pose, projection, root = lifter.fit_pose(best.kept, best.weights, best.params, chosen)
        if camera is None:
            root_position = torch.full_like(root, torch.nan)
            focal = torch.full_like(root[:, 0], torch.nan)
        else:
            k = torch.as_tensor(camera, dtype=torch.float32, device=dev)
            root_position = lifter.root_position(root, projection, chosen.own.frame, k)
            focal = (k[:, 0, 0] + k[:, 1, 1]) / 2
        x = query.joints_2d
        probability = (est.sample_unaries(x[:, None]).exp()[:, 0] - LOG_EPS).clamp(0.0, 1.0)
        if self.joint_calibration is not None:
            probability = self.joint_calibration(probability)
        elapsed = time.perf_counter() - t_start + estimate.timings.get("total", 0.0)
        timings["total"] = 1000 * elapsed
        joints_2d = x.cpu()
        if evidence is None:
            evidence = self.person_evidence(estimate)
        return PipelineResult(
            joints_2d=joints_2d,
            joints_2d_initial=first.joints_2d.cpu(),
            joints_2d_iterations=torch.stack(history, 1).cpu(),
            joints_3d=pose.detach().cpu(),
            root_position=root_position.cpu(),
            focal_px=focal.cpu(),
            focal_assumed=torch.zeros(len(joints_2d), dtype=torch.bool),
            confidence=probability.cpu(),
            facing_camera=estimate.facing_camera.cpu(),
            joint_set=lifter.set_names(best.joint_set),
            psm_energy=torch.stack(energies, 1).cpu(),
            iterations=cfg.iterations,
            timings_ms={name: round(ms, 3) for name, ms in timings.items()},
            image_index=torch.arange(len(joints_2d)),
            box=torch.from_numpy(person_boxes(joints_2d.numpy())).float(),
            score=person_probability(evidence, cfg.search).float(),
            score_evidence=evidence.float(),
            person_found=torch.ones(len(joints_2d), dtype=torch.bool),
        )

    def _iterate(
        self,
        est: Estimate2D,
        query: Query,
        start: torch.Tensor | None,
        cfg: PipelineConfig,
        timings: dict[str, float],
    ) -> tuple[_State, torch.Tensor]:
        """One iteration from the query's 2D pose: the neighbours of every set (projections
        warm-started from `start`, (B x S, 6)), weighted by the image (eq:wt), the refinement
        of every set, and the set chosen by cfg.selection. Adds the stages' ms to timings.
        Returns the chosen set's state and every set's projections (B x S, 6)."""
        lifter, dev = self.lifter, self.lifter.device
        problems = lifter.problems(query, "every")  # the refinement weighs every set
        found = lifter.neighbours(problems, start, timings)
        frame = problems.own.frame
        b = len(query.joints_2d)

        def per_pose(t: torch.Tensor) -> torch.Tensor:  # (B x S, ...) -> (B, S, ...)
            return t.unflatten(0, (b, -1))

        with stage_timer(timings, "weighting", dev):
            scores = neighbour_scores(est, per_pose(project(found.poses, found.params, frame)))
            kept, weights, _ = lifter.weight_neighbours(found.poses, scores.flatten(0, 1))
            kept_2d = project(kept, found.params, frame)
        with stage_timer(timings, "refinement", dev):
            ref = refine(
                est, self.estimator.params, per_pose(kept_2d), per_pose(weights), cfg.refine
            )
            chosen = self._choose(problems, kept, weights, kept_2d, found.params, ref.score, cfg)
        rows = torch.arange(b, device=dev)
        joint_set = problems.joint_set[chosen]
        state = _State(
            kept[chosen],
            weights[chosen],
            found.params[chosen],
            joint_set,
            ref.joints_2d[rows, joint_set],
            ref.score[rows, joint_set],
        )
        return state, found.params

    def _choose(self, problems: Problems, kept, weights, kept_2d, params, posterior, cfg):
        """The chosen problem of each pose (B,): the set of highest refinement posterior
        (B, S) (eqt:best_segments_pose), or of least eq:energyS on its weighted neighbours."""
        if cfg.selection == "posterior":
            return self.lifter.choose(problems, -posterior.flatten())[0]
        residuals = projection_energy(kept_2d, problems.own.joints_2d, problems.masks)
        energy = self.lifter.set_energies(kept, weights, residuals, params, problems)
        return self.lifter.choose(problems, energy)[0]


def _per_image(value, n: int, name: str) -> list:
    """A per-image option given once for every image (a str, a number or None) or as n
    values."""
    if value is None or isinstance(value, str | int | float):
        return [value] * n
    values = list(value)
    if len(values) != n:
        raise ValueError(f"{len(values)} values of {name} for {n} images")
    return values


def _people_asked(people, min_score, n: int) -> tuple[list[str], list[float]]:
    """Pipeline.estimate's people and min_score, one per image, checked."""
    people, min_score = _per_image(people, n, "people"), _per_image(min_score, n, "min_score")
    for wanted, floor in zip(people, min_score, strict=True):
        if wanted not in PEOPLE:
            raise ValueError(f"people must be one of {PEOPLE}, got {wanted!r}")
        if not 0.0 <= floor <= 1.0:
            raise ValueError(f"min_score must lie in [0, 1], got {floor}")
    return people, min_score


def _checked_boxes(images: list[np.ndarray], bboxes) -> list:
    """Pipeline.estimate's bboxes, one entry per image (None: search it), each box checked
    against its image (ds3d.boxes.checked_box)."""
    if bboxes is not None and len(bboxes) != len(images):
        raise ValueError(f"{len(bboxes)} bboxes for {len(images)} images")
    given = [None] * len(images) if bboxes is None else bboxes
    return [
        None if box is None else checked_box(box, image.shape[1], image.shape[0])
        for image, box in zip(images, given, strict=True)
    ]


@dataclass
class _State:
    """What the 3D fit needs from the iteration that chose a person's (x^, s^): the chosen
    set's kept neighbours (B, K_w, 14, 3), weights (B, K_w) and projection (B, 6), the set (B,),
    the refined pose (B, 14, 2) px and its MAP log-posterior (B,)."""

    kept: torch.Tensor
    weights: torch.Tensor
    params: torch.Tensor
    joint_set: torch.Tensor
    joints_2d: torch.Tensor
    score: torch.Tensor

    def merge(self, new: _State) -> _State:
        """Per person, the state with the higher posterior (ties keep self)."""
        take = new.score > self.score

        def pick(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            return torch.where(take.view(-1, *([1] * (a.ndim - 1))), b, a)

        return _State(*(pick(a, b) for a, b in zip(_fields(self), _fields(new), strict=True)))


def _fields(state: _State) -> tuple[torch.Tensor, ...]:
    return tuple(getattr(state, f.name) for f in dataclasses.fields(state))
