"""ds3d.Pipeline: images in, 2D and 3D poses out, by the dual-source approach end to end.

    2D stage         unaries + PSM on a 6-scale pyramid -> x (ds3d.image2d.estimator)
    per iteration t = 1..T (the query is x, then the refined x^ of the previous iteration):
      retrieval      K neighbours per joint set                         (ds3d.lifter)
      projection fit M_s per set (eq:projerr1), warm-started from t - 1 (ds3d.lifter)
      weighting      eq:wt: the unaries summed at each neighbour's projected joints; keep the
                     K_w best and min-max normalise them (eq:wtn)
      refinement     eqt:best_segments_pose: one PSM per (image, set) with the image's unaries
                     and binaries (c = 5 mixtures) fit to the set's weighted projected
                     neighbours; (x^, s^) = the best MAP over the sets
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

import numpy as np
import torch

from ds3d.fit.camera import project
from ds3d.fit.energy import projection_energy
from ds3d.image2d.estimator import LOG_EPS, Estimate2D, EstimatorParams, PoseEstimator2D
from ds3d.image2d.psm import PairwiseMixtures, fit_pairwise_mixtures, infer
from ds3d.inputs import intrinsics_batch
from ds3d.lifter import Lifter, LifterConfig, _timed, image_frame
from ds3d.paths import MODELS_DIR
from ds3d.skeleton import NUM_JOINTS
from ds3d.threads import map_on_threads, split_rows

STEPS_2D = ("features", "traversal", "jointnet", "psm")  # the steps of Estimate2D.timings, s


@dataclass(frozen=True)
class PipelineConfig:
    """Parameters of the image-driven steps (the 3D stage's are in LifterConfig).

    iterations: the paper's default 2. selection: "posterior" (eqt:best_segments_pose) or
    "energy" (eq:energyS; the refined pose is then the chosen set's PSM MAP). components: c of
    the refinement binaries (the paper: 5). min_var: floor of their per-axis variance, in unary
    cells^2 (one cell is `stride` px at the working scale). window_margin: cells of search
    region around the neighbours' projections (search_window). unary_weight: the refinement's
    unaries relative to the 2D stage's (EstimatorParams.unary_weight), against the binaries.
    min_var and unary_weight were chosen on LSP train images held out from the 2D model's
    training (docs/RESULTS.md, pipeline); the margin did not matter there (4 or 8 cells).
    unary_weight 1 weighs the refinement's unaries as the 2D stage does (8x the binaries):
    with the 2D stage's local centroid (EstimatorParams.centroid_radius), 0.5 / 1 / 2 / 4 gave
    43.1 / 43.4 / 43.2 / 42.9 % PCK after iteration 2 on the 300 held-out images, all below
    the 2D stage's own 44.0 % (docs/RESULTS.md, pipeline).
    """

    iterations: int = 2
    selection: str = "posterior"
    components: int = 5
    min_var: float = 4.0
    window_margin: int = 4
    unary_weight: float = 1.0

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


def image_to_cells(points: torch.Tensor, map_to_image: torch.Tensor) -> torch.Tensor:
    """Image px -> unary grid cells (u, v). points: (B, ..., 2); map_to_image: (B, 2, 3), the
    diagonal affine map of Estimate2D. Returns (B, ..., 2) float."""
    shape = (len(points),) + (1,) * (points.ndim - 2) + (2,)
    scale = torch.diagonal(map_to_image[:, :, :2], dim1=1, dim2=2).reshape(shape)
    return (points - map_to_image[:, :, 2].reshape(shape)) / scale


def cells_to_image(cells: torch.Tensor, map_to_image: torch.Tensor) -> torch.Tensor:
    """Unary grid cells (u, v) -> image px; the inverse of image_to_cells. Shapes alike."""
    shape = (len(cells),) + (1,) * (cells.ndim - 2) + (2,)
    scale = torch.diagonal(map_to_image[:, :, :2], dim1=1, dim2=2).reshape(shape)
    return cells * scale + map_to_image[:, :, 2].reshape(shape)


def neighbour_scores(estimate: Estimate2D, projected: torch.Tensor) -> torch.Tensor:
    """eq:wt: the unaries summed at the projected joints of each neighbour.
    projected: (B, S, K, 14, 2) px of the input image. Returns (B, S, K), higher = better."""
    b, s, k = projected.shape[:3]
    return estimate.sample_unaries(projected.reshape(b, s * k, NUM_JOINTS, 2)).sum(-1).view(b, s, k)


@dataclass
class Refinement:
    """The PSM MAP of every (image, set). joints_2d: (B, S, 14, 2) px of the input image;
    score: (B, S) MAP log-posterior (higher is better)."""

    joints_2d: torch.Tensor
    score: torch.Tensor


def search_window(
    unaries: torch.Tensor, cells: torch.Tensor, margin: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cut one image's unaries down to the cells its neighbours' projections span.

    unaries: (14, h, w); cells: (N, 14, 2) grid cells (u, v); margin: cells added on every
    side. Cells beyond the unary grid read log(LOG_EPS), the 2D stage's own padding value, so
    the window depends on the image alone, not on the batch it was padded into. The window
    stays within `margin` cells of the grid: that bounds the work when projections run far off
    the image (e.g. under wrong intrinsics), where a batch's larger padded grid could then give
    an image a wider window than it gets alone.
    Returns the window (14, H, W) and its origin (2,) long (u, v) in the grid.
    """
    h, w = unaries.shape[-2:]
    bound = torch.tensor([w - 1 + margin, h - 1 + margin], device=cells.device)
    flat = torch.nan_to_num(cells.flatten(0, 1), nan=0.0, posinf=1e6, neginf=-1e6)
    lo = (flat.amin(0).floor().long() - margin).clamp(min=-margin).minimum(bound)  # (2,)
    hi = (flat.amax(0).ceil().long() + margin).minimum(bound).maximum(lo)
    u = torch.arange(int(lo[0]), int(hi[0]) + 1, device=cells.device)
    v = torch.arange(int(lo[1]), int(hi[1]) + 1, device=cells.device)
    window = unaries[:, v.clamp(0, h - 1)[:, None], u.clamp(0, w - 1)[None, :]]
    inside = ((v >= 0) & (v < h))[:, None] & ((u >= 0) & (u < w))[None, :]
    return torch.where(inside, window, float(np.log(LOG_EPS))), lo


def refine(
    estimate: Estimate2D,
    params: EstimatorParams,
    neighbours_2d: torch.Tensor,
    weights: torch.Tensor,
    config: PipelineConfig,
) -> Refinement:
    """eqt:best_segments_pose for every (image, set): B * S PSM problems.

    params: the 2D stage's; the refinement's unaries are its log-prob unaries
    (estimate.unaries) times params.unary_weight * config.unary_weight against the binaries,
    and its joints go where params.joint_cells puts them; neighbours_2d: (B, S, N, 14, 2) px,
    the projected neighbours of each set;
    weights: (B, S, N) >= 0, their sample weights in the binaries (eq:binary fit on them with
    `config.components` mixtures, all B * S at once). The MAP of an image's S problems is
    searched together, within `config.window_margin` cells of the span of its neighbours
    (search_window): one window per image rather than the batch's padded grid, which cuts the
    cost of the max-convolutions several fold on LSP images. The weight applies after the
    window is cut, so that cells beyond the grid cost as much as the grid's least likely
    cells (weighting first would make them cheaper, and draw weak joints off the image).
    """
    b, s, n = neighbours_2d.shape[:3]
    unary_weight = params.unary_weight * config.unary_weight
    cells = image_to_cells(neighbours_2d.reshape(b, s * n, NUM_JOINTS, 2), estimate.map_to_image)
    windows = [search_window(estimate.unaries[i], cells[i], config.window_margin) for i in range(b)]
    origin = torch.stack([o for _, o in windows])  # (B, 2)
    local = (cells - origin[:, None, None, :]).reshape(b * s, n, NUM_JOINTS, 2)
    mixtures = fit_pairwise_mixtures(
        local, weights.reshape(b * s, n), n_components=config.components, min_var=config.min_var
    )

    def solve(rows: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(cells (S, 14, 2), score (S,)) of the S problems of each image in rows."""
        out = []
        for i in rows.tolist():
            window, part = windows[i][0], slice(i * s, (i + 1) * s)
            res = infer(
                (unary_weight * window)[None].expand(s, -1, -1, -1),
                PairwiseMixtures(mixtures.mean[part], mixtures.var[part], mixtures.log_gamma[part]),
                stride=1.0,
            )
            out.append(
                (params.joint_cells(window[None].expand(s, -1, -1, -1), res.cells), res.score)
            )
        return out

    # One image at a time (each its own window), so whole images go to parallel threads.
    solved = [one for part in map_on_threads(solve, split_rows(b)) for one in part]
    found = torch.stack([c for c, _ in solved]).view(b, s * NUM_JOINTS, 2) + origin[:, None, :]
    joints_2d = cells_to_image(found, estimate.map_to_image).view(b, s, NUM_JOINTS, 2)
    return Refinement(joints_2d, torch.stack([score for _, score in solved]))


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
        b = len(est.joints_2d)
        k = intrinsics_batch(intrinsics, b)
        x0 = est.joints_2d.to(dev)
        visible = torch.ones(b, NUM_JOINTS, dtype=torch.bool, device=dev)
        # One frame for every iteration: the warm-started projections stay in its coordinates.
        frame = image_frame(x0, visible, None if k is None else k.to(dev))
        usable = lifter.usable_sets(visible)
        rows = torch.arange(b, device=dev)

        x, params = x0, None
        best = None  # per image, the (set, iteration) state with the best posterior so far
        history, energies = [], []
        for _ in range(cfg.iterations):
            with torch.no_grad(), _timed(timings, "retrieval", dev):
                candidates = lifter.retrieve(x)
            with _timed(timings, "projection_fit", dev):
                params, _ = lifter.fit_projections(candidates, x, visible, frame, start=params)
            with torch.no_grad(), _timed(timings, "weighting", dev):
                projected = project(candidates, params, frame.unsqueeze(1))
                kept, weights, _ = lifter.weight_neighbours(
                    candidates, neighbour_scores(est, projected)
                )
                kept_2d = project(kept, params, frame.unsqueeze(1))
            with torch.no_grad(), _timed(timings, "refinement", dev):
                ref = refine(est, self.estimator.params, kept_2d, weights, cfg)
                if cfg.selection == "posterior":
                    chosen = torch.where(usable, ref.score, -torch.inf).argmax(-1)
                else:
                    own_joints = lifter.set_masks[None] * visible[:, None].float()
                    residuals = projection_energy(kept_2d, x[:, None], own_joints)
                    _, chosen = lifter.choose_set(
                        kept, weights, residuals, params, x, visible, frame
                    )
                state = _State(
                    kept,
                    weights,
                    params,
                    chosen,
                    ref.joints_2d[rows, chosen],
                    ref.score[rows, chosen],
                )
                # energy selection has no common measure across iterations: the last one wins
                best = state if best is None or cfg.selection == "energy" else best.merge(state)
            x = best.joints_2d
            history.append(x)
            energies.append(-best.score)

        with _timed(timings, "pose_fit", dev):
            pose = lifter.fit_pose(
                best.kept, best.weights, best.params, x, visible, frame, best.joint_set
            )
        with torch.no_grad():
            probability = est.sample_unaries(x[:, None]).exp()[:, 0] - LOG_EPS
        elapsed = time.perf_counter() - t_start + estimate.timings.get("total", 0.0)
        timings["total"] = 1000 * elapsed
        return PipelineResult(
            joints_2d=x.cpu(),
            joints_2d_initial=x0.cpu(),
            joints_2d_iterations=torch.stack(history, 1).cpu(),
            joints_3d=pose.detach().cpu(),
            confidence=probability.clamp(0.0, 1.0).cpu(),
            facing_camera=estimate.facing_camera.cpu(),
            joint_set=[lifter.config.joint_sets[i] for i in best.joint_set.tolist()],
            psm_energy=torch.stack(energies, 1).cpu(),
            iterations=cfg.iterations,
            timings_ms={name: round(ms, 3) for name, ms in timings.items()},
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
