"""The two continuous fits of the paper, each a batch of small robust least-squares problems
solved by ds3d.fit.gauss_newton with analytic Jacobians.

- fit_projection (eq:projerr1): the projection M_s that best maps a set's K retrieved poses onto
  the 2D pose, one problem per (image, joint set).
- fit_pose (eq:energyMin2): the 3D pose, in the PCA space of the weighted neighbours, that
  minimises w_p E_p + w_r E_r + w_a E_a with the chosen projection held fixed; and, beyond the
  paper, the person's proportions: one scale per bone group (ds3d.fit.bones), held near the
  database's by a Gaussian prior on its logarithm.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ds3d.fit import gauss_newton
from ds3d.fit.bones import (
    bone_lengths,
    group_spread,
    scale_derivatives,
    scaling_map,
    with_bone_lengths,
)
from ds3d.fit.camera import (
    CameraFrame,
    initial_params,
    project_rotated,
    rotate,
    rotation_matrix,
    rotation_vector,
)
from ds3d.fit.eigen import symmetric_eigh
from ds3d.fit.energy import limb_lengths, limb_vectors
from ds3d.fit.gauss_newton import Residuals
from ds3d.skeleton import BONE_GROUPS, NUM_JOINTS


def joint_weights(mask: torch.Tensor) -> torch.Tensor:
    """E_p's per-joint weights: the mask rescaled to 14 joints (ds3d.fit.energy). (..., 14)."""
    return mask * (NUM_JOINTS / mask.sum(-1, keepdim=True).clamp_min(1))


def fit_projection(
    candidates: torch.Tensor,
    joints_2d: torch.Tensor,
    mask: torch.Tensor,
    frame: CameraFrame,
    start: torch.Tensor | None = None,
    iterations: int = 1,
) -> torch.Tensor:
    """eq:projerr1 for P independent problems: the mean over the K neighbours of E_p.

    candidates: (P, K, 14, 3) mm, camera-oriented; joints_2d: (P, 14, 2) px; mask: (P, 14) float
    (the set's visible joints); frame: leading dim P; start: optional (P, 6) warm start.
    Returns params (P, 6).
    """
    if start is None:
        start = initial_params(candidates, joints_2d, mask, frame)
    evaluate = projection_problem(candidates, joints_2d, mask, frame)
    state = torch.cat([rotation_matrix(start[:, :3]).flatten(1), start[:, 3:]], 1)
    state, _ = gauss_newton.minimize(evaluate, state, iterations, retract=turn)
    return torch.cat([rotation_vector(state[:, :9].view(-1, 3, 3)), state[:, 9:]], 1)


def projection_problem(candidates, joints_2d, mask, frame: CameraFrame) -> gauss_newton.Evaluate:
    """eq:projerr1's residuals as ds3d.fit.gauss_newton takes them (arguments as fit_projection).
    The state (P, 12) is (R (9), a, b, w); its unknowns (P, 6) are (d, a, b, w), a rotation
    being moved as exp(d) R (`turn`), never through the axis-angle's own derivative."""
    root_weight = joint_weights(mask).sqrt()[:, None, :, None]  # (P, 1, 14, 1)
    term_weight = candidates.new_full(candidates.shape[:2], 1.0 / candidates.shape[1])

    def evaluate(state: torch.Tensor, with_jacobian: bool) -> list[Residuals]:
        rotated = rotate(candidates, state[:, :9].view(-1, 3, 3))
        out = project_rotated(rotated, state[:, 9:], frame, with_jacobian)
        uv = out[0] if with_jacobian else out
        value = ((uv - joints_2d[:, None]) * root_weight).flatten(2)  # (P, K, 28)
        if not with_jacobian:
            return [Residuals(term_weight, value)]
        _, d_points, d_shift = out
        # d uv / d d = d_points @ -[R X]_x, row by row the cross product R X x d_points[row]
        d_rotation = torch.linalg.cross(rotated[..., None, :], d_points)  # (P, K, 14, 2, 3)
        jacobian = torch.cat([d_rotation, d_shift], -1) * root_weight[..., None]
        return [Residuals(term_weight, value, jacobian.flatten(2, 3))]

    return evaluate


def turn(state: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """State (P, 12) = (R, a, b, w) moved by step (P, 6) = (d, da, db, dw): R -> exp(d) R."""
    rotation = rotation_matrix(step[:, :3]) @ state[:, :9].view(-1, 3, 3)
    return torch.cat([rotation.flatten(1), state[:, 9:] + step[:, 3:]], 1)


def weighted_pca(poses: torch.Tensor, weights: torch.Tensor, components: int):
    """poses: (B, K, 14, 3); weights: (B, K) >= 0. Returns mean (B, 42), basis (B, C, 42) with
    orthonormal rows ordered by weighted variance, and the standard deviation along each (B, C)
    mm; C = min(components, K, 42)."""
    flat = poses.flatten(-2)
    w = weights / weights.sum(-1, keepdim=True).clamp_min(1e-12)
    mean = (w[..., None] * flat).sum(-2)
    centred = (flat - mean[..., None, :]) * w.sqrt()[..., None]
    # the eigenvectors of the (42, 42) scatter: the right singular vectors of `centred`, at
    # less than half the cost of its SVD
    variance, vectors = symmetric_eigh(centred.transpose(-1, -2) @ centred)
    c = min(components, *centred.shape[-2:])
    top = vectors.flip(-1)[..., :c].transpose(-1, -2)  # eigh sorts ascending
    return mean, top, variance.flip(-1)[..., :c].clamp_min(0).sqrt()


@dataclass(frozen=True)
class EnergyWeights:
    """omega_p, omega_r, omega_a of eq:energyMin (the paper's values), and omega_g, the weight
    of the prior on the person's bone-group scales: omega_g * sum_g (log scale_g / sd_g)^2,
    sd_g from ds3d.fit.bones.GROUP_LOG_SD normalised to an RMS of one (omega_g chosen by
    leave-one-subject-out on the training subjects: docs/tuning.md)."""

    projection: float = 0.55
    retrieval: float = 0.35
    anthropometric: float = 0.065
    proportions: float = 0.5
    # omega_l: E_l, the squared distance of the person from the learnt prior's pose (in
    # LEARNT_UNIT), where one is given (ds3d.mocap.prior). Stronger, clean 2D gains and other
    # proportions than the database's lose (S9: docs/tuning.md)
    learnt: float = 0.1


def fit_pose(
    neighbours: torch.Tensor,
    weights: torch.Tensor,
    params: torch.Tensor,
    joints_2d: torch.Tensor,
    mask: torch.Tensor,
    frame: CameraFrame,
    omega: EnergyWeights = EnergyWeights(),
    components: int = 18,
    iterations: int = 4,
    proportions: bool = True,
    learnt: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """eq:energyMin2 for B problems, with the person's bone-group scales when `proportions`.

    neighbours: (B, K, 14, 3) mm camera-oriented; weights: (B, K) in [0, 1]; params: (B, 6) the
    chosen projection; joints_2d: (B, 14, 2) px; mask: (B, 14) float, the joints E_p uses.
    E_r and E_a hold the pose in the database's proportions near the neighbours; E_p sees it
    with the person's. learnt: optional (B, 14, 3) mm, a learnt prior's pose of the person in
    the neighbours' orientation: the fit starts there, may move along it (one more direction
    beside the neighbours' components) and E_l (omega.learnt) holds the person near it.
    Returns that pose (B, 14, 3) mm in the neighbours' orientation and the
    projection (B, 6): the given one, its position and depth refitted with the proportions
    (a person's size and distance are one unknown in an image; the prior on the scales, which
    prefers the database's proportions, settles it).
    """
    problem = PoseProblem(neighbours, weights, components, proportions, learnt)
    strength = params.new_ones(len(params))  # the prior's, per problem
    evaluate = problem.residuals(params, joints_2d, mask, frame, omega, strength)
    if not proportions:
        z, _ = gauss_newton.minimize(evaluate, problem.start(), iterations)
        return problem.person(z), problem.projection(z, params)
    # Noisy 2D would be explained by odd proportions: half the steps with the prior as set,
    # then the prior strengthened where the pose still misses its 2D joints by more than
    # NOISE_REFERENCE of its spread (a misfit the proportions could not explain: noise).
    first = iterations // 2
    z, _ = gauss_newton.minimize(evaluate, problem.start(), first)
    (projection_term, *_) = evaluate(z, False)
    misfit = (projection_term.squared[:, 0] / NUM_JOINTS).sqrt() / frame.spread
    # evaluate reads it; at most 100x, the database's proportions in effect, beyond which the
    # normal equations grow ill-conditioned in float32
    strength.copy_(((misfit / NOISE_REFERENCE).clamp_min(1) ** 4).clamp_max(100))
    z, _ = gauss_newton.minimize(evaluate, z, iterations - first)
    return problem.person(z), problem.projection(z, params)


# The RMS 2D misfit, as a fraction of the 2D pose's spread, beyond which the prior on a
# person's proportions strengthens (as its fourth power): after the first steps the median is
# 0.02 for clean 2D and for rescaled bodies, 0.08 with 10 px of noise (S9, docs/tuning.md).
NOISE_REFERENCE = 0.04
# The spread of the prior that holds the projection's (a, b, w) where the 2D is noisy: 5 % of the
# pose's spread and of its depth (S9: noisy 72.4 -> 71.3 mm, clean and rescaled unchanged).
SHIFT_SD = 0.05
# E_l's unit, mm: omega_l sum_j |X_j - L_j|^2 / LEARNT_UNIT^2 over the person's joints X and the
# learnt pose's L (the order of the prior's own joint errors)
LEARNT_UNIT = 100.0


# The learnt pose's bones are held within this factor of the neighbours' (their weighted mean): a
# network's answer to an ambiguous depth averages a limb's ways and shortens it (a forearm of
# 95 mm on an LSP photo); on Human3.6M S9 no figure moves (docs/tuning.md).
LEARNT_BONE_BAND = 1.25


def within_band(learnt: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """learnt (B, 14, 3) mm with each bone's length clamped to within LEARNT_BONE_BAND of
    lengths (B, 14) mm (one per ds3d.skeleton.BONES), its direction kept."""
    own = bone_lengths(learnt)
    held = torch.minimum(torch.maximum(own, lengths / LEARNT_BONE_BAND), lengths * LEARNT_BONE_BAND)
    return with_bone_lengths(learnt, held)


class PoseProblem:
    """eq:energyMin2's unknowns z (B, C + G + T): C PCA coefficients of the weighted
    neighbours, in standard deviations (every direction the same scale for the solver), and
    with a learnt pose (B, 14, 3) one more, along the learnt pose's difference from their mean
    (1: the learnt pose, where the fit starts); with `proportions`, G log scales of the bone
    groups and T = 3 changes of the projection's (a, b, w) (none of either without)."""

    def __init__(self, neighbours, weights, components: int, proportions: bool, learnt=None):
        self.neighbours = neighbours
        self.learnt = learnt
        self.share = weights / weights.sum(-1, keepdim=True).clamp_min(1e-12)  # weighted means
        mean, basis, sigma = weighted_pca(neighbours, weights, components)
        self.mean = mean.unflatten(-1, (NUM_JOINTS, 3))  # (B, 14, 3)
        self.basis = (basis * sigma.clamp_min(1e-3)[..., None]).unflatten(-1, (NUM_JOINTS, 3))
        if learnt is not None:
            lengths = (self.share[..., None] * bone_lengths(neighbours)).sum(-2)  # (B, 14), BONES
            self.learnt = learnt = within_band(learnt, lengths)
            self.basis = torch.cat([self.basis, (learnt - self.mean)[:, None]], 1)
        self.components = c = self.basis.shape[1]
        self.groups = g = len(BONE_GROUPS) if proportions else 0
        self.shifts = 3 if proportions else 0
        self.scale_columns = slice(c, c + g)
        self.shift_columns = slice(c + g, c + g + self.shifts)

    def start(self) -> torch.Tensor:
        """(B, C + G + T): the neighbours' mean, or the learnt pose where one is given."""
        unknowns = self.components + self.groups + self.shifts
        z = self.mean.new_zeros(len(self.mean), unknowns)
        if self.learnt is not None:
            z[:, self.components - 1] = 1
        return z

    def pose(self, z: torch.Tensor) -> torch.Tensor:
        """(B, 14, 3) mm: the pose in the database's proportions."""
        offset = z[:, None, : self.components] @ self.basis.flatten(2)  # (B, 1, 42)
        return self.mean + offset.view_as(self.mean)

    def person(self, z: torch.Tensor) -> torch.Tensor:
        """(B, 14, 3) mm: the pose with the person's bone-group scales."""
        pose = self.pose(z)
        return scaling_map(z[:, self.scale_columns].exp()) @ pose if self.groups else pose

    def projection(self, z: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
        """(B, 6): params with z's changes of (a, b, w)."""
        if not self.shifts:
            return params
        return torch.cat([params[:, :3], params[:, 3:] + z[:, self.shift_columns]], 1)

    def residuals(
        self,
        params,
        joints_2d,
        mask,
        frame: CameraFrame,
        omega: EnergyWeights,
        prior_strength: torch.Tensor,
    ):
        """The energy's residuals as ds3d.fit.gauss_newton takes them: E_p of the person under
        the projection params (B, 6), E_r and E_a of the pose, E_l of the person where a learnt
        pose is given, the prior on the scales (omega.proportions times prior_strength (B,),
        read at each evaluation) and, with the strength beyond one, on the projection's change
        (in SHIFT_SD)."""
        b, c, g = len(self.mean), self.components, self.groups
        n = c + g + self.shifts
        rotation = rotation_matrix(params[:, :3])
        root_weight = joint_weights(mask).sqrt()[..., None, None]  # (B, 14, 1, 1)
        neighbour_vectors = self.neighbours.flatten(-2)
        neighbour_limbs = limb_lengths(self.neighbours)
        limb_basis = limb_vectors(self.basis)  # (B, C, 13, 3): the limbs' change per coefficient
        ones = self.mean.new_ones(b, 1)
        # Jacobians of the terms that only the pose moves: zero beyond its coefficients
        d_pose = F.pad(self.basis.flatten(2).transpose(1, 2), (0, n - c))[:, None]  # (B,1,42,n)
        # the scales' prior in units of each group's spread, normalised to an RMS of one
        prior_sd = group_spread().to(self.mean)[:g]
        prior_jacobian = torch.eye(g, n, dtype=self.mean.dtype, device=self.mean.device)
        prior_jacobian = (prior_jacobian.roll(c, -1) / prior_sd[:, None]).expand(b, 1, g, n)
        shift_jacobian = torch.eye(3, n, dtype=self.mean.dtype, device=self.mean.device)
        shift_jacobian = (shift_jacobian.roll(c + g, -1) / SHIFT_SD).expand(b, 1, 3, n)

        def evaluate(z: torch.Tensor, with_jacobian: bool) -> list[Residuals]:
            pose, scales = self.pose(z), z[:, self.scale_columns].exp()
            scaling = scaling_map(scales) if g else None
            person = pose if scaling is None else scaling @ pose
            shift = self.projection(z, params)[:, 3:]
            out = project_rotated(rotate(person[:, None], rotation), shift, frame, with_jacobian)
            uv = (out[0] if with_jacobian else out)[:, 0]
            limbs_3d = limb_vectors(pose)  # (B, 13, 3)
            limbs = limbs_3d.norm(dim=-1)
            groups = [
                Residuals(
                    omega.projection * ones,
                    ((uv - joints_2d) * root_weight[..., 0]).flatten(1)[:, None],  # (B, 1, 28)
                ),
                Residuals(
                    omega.retrieval * self.share, pose.flatten(1)[:, None] - neighbour_vectors
                ),
                Residuals(omega.anthropometric * self.share, limbs[:, None] - neighbour_limbs),
            ]
            if g:
                scale_prior = (z[:, self.scale_columns] / prior_sd)[:, None]
                prior_weight = omega.proportions * prior_strength[:, None]
                groups.append(Residuals(prior_weight, scale_prior, robust=False))
                # where the 2D is noisy, the projection's position and depth held too
                held = omega.proportions * (prior_strength[:, None] - 1)
                shift_prior = (z[:, self.shift_columns] / SHIFT_SD)[:, None]
                groups.append(Residuals(held, shift_prior, robust=False))
            if self.learnt is not None:
                # quadratic: a robust term would pin the fit to the learnt pose where it starts
                # (its fourth root of the squared distance has an infinite slope at zero)
                near_learnt = ((person - self.learnt) / LEARNT_UNIT).flatten(1)[:, None]
                groups.append(Residuals(omega.learnt * ones, near_learnt, robust=False))
            if not with_jacobian:
                return groups
            d_person = self.basis.permute(0, 2, 3, 1)  # (B, 14, 3, C)
            if g:
                through_scaling = (scaling @ d_person.flatten(2)).view(b, NUM_JOINTS, 3, c)
                d_person = torch.cat([through_scaling, scale_derivatives(pose, scales)], -1)
            d_uv = out[1][:, 0] @ rotation[:, None]  # (B, 14, 2, 3): d uv / d person
            d_uv = (d_uv[..., None] * d_person[:, :, None]).sum(-2)  # (B, 14, 2, C + G)
            if self.shifts:
                d_uv = torch.cat([d_uv, out[2][:, 0]], -1)
            groups[0].jacobian = (d_uv * root_weight).flatten(1, 2)[:, None]
            groups[1].jacobian = d_pose
            unit = limbs_3d / limbs.clamp_min(1e-6)[..., None]  # (B, 13, 3)
            d_limbs = (unit[:, None] * limb_basis).sum(-1).transpose(1, 2)  # (B, 13, C)
            groups[2].jacobian = F.pad(d_limbs, (0, n - c))[:, None]
            if g:
                groups[3].jacobian = prior_jacobian
                groups[4].jacobian = shift_jacobian
            if self.learnt is not None:
                d_learnt = F.pad(d_person.flatten(1, 2), (0, self.shifts)) / LEARNT_UNIT
                groups[-1].jacobian = d_learnt[:, None]
            return groups

        return evaluate
