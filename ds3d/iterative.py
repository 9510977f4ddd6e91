"""The paper's iterative approach (sec:iter): the 3D stage of people posed in images, where the
image's 2D evidence weighs the retrieved poses and the retrieved poses refine the 2D pose.

    per iteration t = 1..T (the query is x, then the refined x^ of the previous iteration):
      retrieval      K neighbours per joint set                         (ds3d.lifter)
      projection fit M_s per set (eq:projerr1), warm-started from t - 1 (ds3d.lifter)
      weighting      eq:wt: the unaries summed at each neighbour's projected joints; keep the
                     K_w best and min-max normalise them (eq:wtn)
      refinement     eqt:best_segments_pose: one PSM per (image, set) with the image's
                     unaries and binaries (c = 5 mixtures) fit to the set's weighted
                     projected neighbours; (x^, s^) = the best MAP over the sets (ds3d.refine)
    3D fit           eq:energyMin2 once, on the chosen set, with E_p measured against x^

The unaries are computed once, by the 2D stage; later iterations reuse them.

Iterations never make the refinement worse by its own measure: the pair (x^, s^) is the argmax
of the posterior over the sets of every iteration run so far, so the PSM energy (the negative
MAP log-posterior) of the answer after iteration t + 1 is at most that after t. Comparing the
models of two iterations is the same comparison eqt:best_segments_pose makes between the models
of two joint sets (each a PSM with the same unaries and its own data-driven binaries).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from ds3d.fit.camera import project
from ds3d.fit.energy import projection_energy
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.result import Estimate2D
from ds3d.lifter import Lifter, Query
from ds3d.refine import RefineParams, refine
from ds3d.skeleton import NUM_JOINTS
from ds3d.util.timing import stage_timer

SELECTIONS = (
    "posterior",
    "energy",
)  # how the joint set is chosen: eqt:best_segments_pose, eq:energyS


@dataclass
class Lifted:
    """B people lifted from their images, on the lifter's device: joints_2d (B, 14, 2) px, the
    refined pose x^; joints_2d_initial (B, 14, 2), the 2D stage's x; joints_2d_iterations
    (B, T, 14, 2), x^ after each iteration; psm_energy (B, T), its negative MAP log-posterior;
    joints_3d (B, 14, 3) mm, camera-oriented, root at the hip midpoint; joint_set (B,) long, the
    chosen set s^ (an index into LifterConfig.joint_sets); root_position (B, 3) mm, the hip
    midpoint in the coordinates of the camera given (NaN without one)."""

    joints_2d: torch.Tensor
    joints_2d_initial: torch.Tensor
    joints_2d_iterations: torch.Tensor
    psm_energy: torch.Tensor
    joints_3d: torch.Tensor
    joint_set: torch.Tensor
    root_position: torch.Tensor


@torch.inference_mode()
def lift_with_image(
    lifter: Lifter,
    model: EstimatorParams,
    estimate: Estimate2D,
    iterations: int,
    selection: str,
    refine_params: RefineParams,
    intrinsics: torch.Tensor | None = None,
    camera: torch.Tensor | None = None,
    timings: dict[str, float] | None = None,
) -> Lifted:
    """The module's steps for the B people of a 2D estimate (B >= 1; model: the 2D model's
    parameters, whose grid the unaries are on). selection: "posterior" or "energy" (SELECTIONS;
    with "energy" the refined pose is the chosen set's PSM MAP). intrinsics: optional (B, 3, 3),
    the camera the 2D poses were taken by (the projection's frame; without: weak perspective);
    camera: optional (B, 3, 3), the intrinsics of the camera in whose coordinates to place the
    people. Adds each stage's ms to `timings`."""
    timings = {} if timings is None else timings
    dev = lifter.device
    est = dataclasses.replace(
        estimate, unaries=estimate.unaries.to(dev), map_to_image=estimate.map_to_image.to(dev)
    )
    # One frame for every iteration: the warm-started projections stay in its coordinates.
    joints = est.joints_2d.to(dev)
    visible = torch.ones(joints.shape[:2], dtype=torch.bool, device=dev)
    first = Query.of(joints, visible, None if intrinsics is None else intrinsics.to(dev))
    query = first
    best: _State | None = None  # per person, the state with the best posterior so far
    start = None  # every set's projections of the iteration before, for a warm start
    history, energies = [], []
    for _ in range(iterations):
        state, start = _iterate(lifter, model, est, query, start, selection, refine_params, timings)
        # energy selection has no common measure across iterations: the last one wins
        best = state if best is None or selection == "energy" else best.merge(state)
        query = query.moved_to(best.joints_2d)
        history.append(best.joints_2d)
        energies.append(-best.score)
    assert best is not None, "at least one iteration"
    with stage_timer(timings, "pose_fit", dev):
        chosen = lifter.problems(query, best.joint_set)
        pose, projection, root = lifter.fit_pose(best.kept, best.weights, best.params, chosen)
    if camera is None:
        root_position = torch.full_like(root, torch.nan)
    else:
        k = torch.as_tensor(camera, dtype=torch.float32, device=dev)
        root_position = lifter.root_position(root, projection, chosen.own.frame, k)
    return Lifted(
        joints_2d=query.joints_2d,
        joints_2d_initial=first.joints_2d,
        joints_2d_iterations=torch.stack(history, 1),
        psm_energy=torch.stack(energies, 1),
        joints_3d=pose.detach(),
        joint_set=best.joint_set,
        root_position=root_position,
    )


def neighbour_scores(estimate: Estimate2D, projected: torch.Tensor) -> torch.Tensor:
    """eq:wt: the unaries summed at the projected joints of each neighbour.
    projected: (B, S, K, 14, 2) px of the input image. Returns (B, S, K), higher = better."""
    b, s, k = projected.shape[:3]
    return estimate.sample_unaries(projected.reshape(b, s * k, NUM_JOINTS, 2)).sum(-1).view(b, s, k)


def _iterate(
    lifter: Lifter,
    model: EstimatorParams,
    est: Estimate2D,
    query: Query,
    start: torch.Tensor | None,
    selection: str,
    refine_params: RefineParams,
    timings: dict[str, float],
) -> tuple[_State, torch.Tensor]:
    """One iteration from the query's 2D pose: the neighbours of every set (projections
    warm-started from `start`, (B x S, 6)), weighted by the image (eq:wt), the refinement of
    every set, and the set chosen by `selection`. Adds the stages' ms to timings. Returns the
    chosen set's state and every set's projections (B x S, 6)."""
    dev = lifter.device
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
        ref = refine(est, model, per_pose(kept_2d), per_pose(weights), refine_params)
        if selection == "posterior":
            cost = -ref.score.flatten()
        else:
            residuals = projection_energy(kept_2d, problems.own.joints_2d, problems.masks)
            cost = lifter.set_energies(kept, weights, residuals, found.params, problems)
        chosen = lifter.choose(problems, cost)[0]
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

        fields = [f.name for f in dataclasses.fields(self)]
        return _State(*(pick(getattr(self, f), getattr(new, f)) for f in fields))
