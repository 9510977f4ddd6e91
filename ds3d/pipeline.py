"""ds3d.Pipeline: images in, 2D and 3D poses out, by the dual-source approach end to end.

    2D stage         unaries + PSM on a 6-scale pyramid -> x (ds3d.image2d.estimator)
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
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from ds3d.fit.camera import project
from ds3d.fit.energy import projection_energy
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.result import LOG_EPS, Estimate2D
from ds3d.lifter import Lifter, LifterConfig, Query
from ds3d.paths import MODELS_DIR
from ds3d.refine import RefineParams, refine
from ds3d.skeleton import NUM_JOINTS
from ds3d.timing import stage_timer

STEPS_2D = ("features", "traversal", "jointnet", "psm")  # the steps of Estimate2D.timings, s


@dataclass(frozen=True)
class PipelineConfig(RefineParams):
    """Parameters of the image-driven steps (the 3D stage's are in LifterConfig): the
    refinement's (RefineParams), the number of iterations (the paper's 2; with the bundled 2D stage
    the second adds nothing measurable: docs/RESULTS.md) and how the joint set is chosen:
    "posterior" (eqt:best_segments_pose) or "energy" (eq:energyS; the refined pose is then the
    chosen set's PSM MAP)."""

    iterations: int = 1
    selection: str = "posterior"

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.selection not in ("posterior", "energy"):
            raise ValueError(f"selection must be 'posterior' or 'energy', got {self.selection!r}")


@dataclass
class PipelineResult:
    """Poses of B images.

    joints_2d: (B, 14, 2) float32 px of the input image, the refined 2D pose x^ (final).
    joints_2d_initial: (B, 14, 2) float32 px, the 2D stage's pose x.
    joints_2d_iterations: (B, T, 14, 2) float32 px, x^ after each iteration.
    joints_3d: (B, 14, 3) float32 mm, camera-oriented (x right, y down, z away from the camera),
        root at the hip midpoint.
    confidence: (B, 14) float32 in [0, 1], the 2D stage's joint probability at x^.
    facing_camera: (B,) float32 in [0, 1], the 2D stage's probability that the person faces the
        camera; below 0.5 its left and right were swapped (Estimate2D.facing_camera), so a
        value near 0.5 says the left/right labels are a guess.
    joint_set: B names, the chosen set s^.
    psm_energy: (B, T) float32, the negative MAP log-posterior of x^ after each iteration
        (non-increasing in t with selection "posterior", which keeps the better pose; with
        "energy" the last iteration's pose is kept).
    iterations: T, the number of iterations run.
    timings_ms: wall time of each stage for the whole batch.
    """

    joints_2d: torch.Tensor
    joints_2d_initial: torch.Tensor
    joints_2d_iterations: torch.Tensor
    joints_3d: torch.Tensor
    confidence: torch.Tensor
    facing_camera: torch.Tensor
    joint_set: list[str]
    psm_energy: torch.Tensor
    iterations: int
    timings_ms: dict[str, float]

    def item(self, i: int) -> dict:
        """Image i's result as JSON-ready lists."""
        return {
            "joints_2d": self.joints_2d[i].tolist(),
            "joints_2d_initial": self.joints_2d_initial[i].tolist(),
            "joints_3d": self.joints_3d[i].tolist(),
            "confidence": self.confidence[i].tolist(),
            "facing_camera": float(self.facing_camera[i]),
            "joint_set": self.joint_set[i],
            "iterations": self.iterations,
            "psm_energy": self.psm_energy[i].tolist(),
        }


def neighbour_scores(estimate: Estimate2D, projected: torch.Tensor) -> torch.Tensor:
    """eq:wt: the unaries summed at the projected joints of each neighbour.
    projected: (B, S, K, 14, 2) px of the input image. Returns (B, S, K), higher = better."""
    b, s, k = projected.shape[:3]
    return estimate.sample_unaries(projected.reshape(b, s * k, NUM_JOINTS, 2)).sum(-1).view(b, s, k)


class Pipeline:
    """Load once, estimate many: `Pipeline.load().estimate(images)`."""

    def __init__(
        self, estimator: PoseEstimator2D, lifter: Lifter, config: PipelineConfig = PipelineConfig()
    ):
        self.estimator = estimator
        self.lifter = lifter
        self.config = config

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
        """The models of `model_dir` (default models/): the 2D stage in `image2d`, the pose
        database in `database`. Raises DataFormatError when either is missing or malformed."""
        directory = Path(model_dir) if model_dir is not None else MODELS_DIR
        estimator = PoseEstimator2D.load(directory / image2d)
        lifter_config = LifterConfig() if lifter_config is None else lifter_config
        lifter = Lifter.load(directory, device=device, config=lifter_config, database=database)
        return cls(estimator, lifter, config)

    @property
    def model_id(self) -> str:
        return self.lifter.model_id

    def estimate(
        self, images, bboxes=None, intrinsics=None, iterations: int | None = None
    ) -> PipelineResult:
        """2D and 3D poses of B images.

        images: B arrays (H_i, W_i, 3) uint8 RGB; bboxes: None or B entries, each None or a
        person box (x0, y0, x1, y1) px; intrinsics: None (weak perspective) or (B, 3, 3) / (3, 3)
        pinhole matrices; iterations: overrides config.iterations. Raises InvalidImage,
        InvalidPose (bad intrinsics) or ValueError (bad boxes).
        """
        estimate = self.estimator.estimate(list(images), bboxes)
        return self.lift_estimate(estimate, intrinsics, iterations)

    @torch.inference_mode()
    def lift_estimate(
        self, estimate: Estimate2D, intrinsics=None, iterations: int | None = None
    ) -> PipelineResult:
        """Everything after the 2D stage, on its result for B images (arguments as estimate):
        lets a caller run several configurations on one 2D estimate."""
        cfg = self.config
        if iterations is not None:
            cfg = dataclasses.replace(cfg, iterations=iterations)
        lifter, dev = self.lifter, self.lifter.device
        t_start = time.perf_counter()
        timings = {f"2d_{step}": 1000 * estimate.timings.get(step, 0.0) for step in STEPS_2D}
        est = dataclasses.replace(
            estimate, unaries=estimate.unaries.to(dev), map_to_image=estimate.map_to_image.to(dev)
        )
        # One frame for every iteration: the warm-started projections stay in its coordinates.
        first = lifter.query(est.joints_2d.to(dev), None, intrinsics)
        query, best = first, None  # best: per image, the state with the best posterior so far
        start = None  # the projections of the iteration before, for a warm start
        history, energies = [], []
        for _ in range(cfg.iterations):
            state = self._iterate(est, query, start, cfg, timings)
            start = state.params
            # energy selection has no common measure across iterations: the last one wins
            best = state if best is None or cfg.selection == "energy" else best.merge(state)
            query = query.moved_to(best.joints_2d)
            history.append(best.joints_2d)
            energies.append(-best.score)

        with stage_timer(timings, "pose_fit", dev):
            pose, _ = lifter.fit_pose(best.kept, best.weights, best.params, query, best.joint_set)
        x = query.joints_2d
        probability = est.sample_unaries(x[:, None]).exp()[:, 0] - LOG_EPS
        elapsed = time.perf_counter() - t_start + estimate.timings.get("total", 0.0)
        timings["total"] = 1000 * elapsed
        return PipelineResult(
            joints_2d=x.cpu(),
            joints_2d_initial=first.joints_2d.cpu(),
            joints_2d_iterations=torch.stack(history, 1).cpu(),
            joints_3d=pose.detach().cpu(),
            confidence=probability.clamp(0.0, 1.0).cpu(),
            facing_camera=estimate.facing_camera.cpu(),
            joint_set=[lifter.config.joint_sets[i] for i in best.joint_set.tolist()],
            psm_energy=torch.stack(energies, 1).cpu(),
            iterations=cfg.iterations,
            timings_ms={name: round(ms, 3) for name, ms in timings.items()},
        )

    def _iterate(
        self,
        est: Estimate2D,
        query: Query,
        start: torch.Tensor | None,
        cfg: PipelineConfig,
        timings: dict[str, float],
    ) -> _State:
        """One iteration from the query's 2D pose: neighbours (projections warm-started from
        `start`, (B, S, 6)), weighted by the image (eq:wt), the refinement of every set, and
        the set chosen by cfg.selection. Adds the stages' ms to timings."""
        lifter, dev = self.lifter, self.lifter.device
        found = lifter.neighbours(query, start, timings)
        frame = query.frame.unsqueeze(1)
        with stage_timer(timings, "weighting", dev):
            scores = neighbour_scores(est, project(found.poses, found.params, frame))
            kept, weights, _ = lifter.weight_neighbours(found.poses, scores)
            kept_2d = project(kept, found.params, frame)
        with stage_timer(timings, "refinement", dev):
            ref = refine(est, self.estimator.params, kept_2d, weights, cfg)
            if cfg.selection == "posterior":
                usable = lifter.usable_sets(query.visible)
                chosen = torch.where(usable, ref.score, -torch.inf).argmax(-1)
            else:
                own_joints = lifter.set_masks[None] * query.visible[:, None].float()
                residuals = projection_energy(kept_2d, query.joints_2d[:, None], own_joints)
                _, chosen = lifter.choose_set(kept, weights, residuals, found.params, query)
        rows = torch.arange(len(chosen), device=dev)
        return _State(
            kept,
            weights,
            found.params,
            chosen,
            ref.joints_2d[rows, chosen],
            ref.score[rows, chosen],
        )


@dataclass
class _State:
    """What the 3D fit needs from the iteration that chose an image's (x^, s^): the kept
    neighbours (B, S, K_w, 14, 3), weights (B, S, K_w), projections (B, S, 6), the set (B,),
    the refined pose (B, 14, 2) px and its MAP log-posterior (B,)."""

    kept: torch.Tensor
    weights: torch.Tensor
    params: torch.Tensor
    joint_set: torch.Tensor
    joints_2d: torch.Tensor
    score: torch.Tensor

    def merge(self, new: _State) -> _State:
        """Per image, the state with the higher posterior (ties keep self)."""
        take = new.score > self.score

        def pick(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            return torch.where(take.view(-1, *([1] * (a.ndim - 1))), b, a)

        return _State(*(pick(a, b) for a, b in zip(_fields(self), _fields(new), strict=True)))


def _fields(state: _State) -> tuple[torch.Tensor, ...]:
    return tuple(getattr(state, f.name) for f in dataclasses.fields(state))
