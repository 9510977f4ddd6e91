"""The two continuous fits of the paper, each a batch of small L-BFGS problems.

- fit_projection (eq:projerr1): the projection M_s that best maps a set's K retrieved poses onto
  the 2D pose, one problem per (image, joint set).
- fit_pose (eq:energyMin2): the 3D pose, in the PCA space of the weighted neighbours, that
  minimises w_p E_p + w_r E_r + w_a E_a with the chosen projection held fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ds3d.fit.camera import CameraFrame, initial_params, project
from ds3d.fit.energy import limb_lengths, projection_energy, weighted_robust_distance
from ds3d.fit.lbfgs import minimize


def fit_projection(
    candidates: torch.Tensor,
    joints_2d: torch.Tensor,
    mask: torch.Tensor,
    frame: CameraFrame,
    start: torch.Tensor | None = None,
    iterations: int = 20,
) -> tuple[torch.Tensor, torch.Tensor]:
    """eq:projerr1 for P independent problems.

    candidates: (P, K, 14, 3) mm, camera-oriented; joints_2d: (P, 14, 2) px; mask: (P, 14) float
    (the set's visible joints); frame: leading dim P; start: optional (P, 6) warm start.
    Returns params (P, 6) and the per-candidate projection energies (P, K) at the optimum.
    """
    if start is None:
        start = initial_params(candidates, joints_2d, mask, frame)

    def energy(params: torch.Tensor) -> torch.Tensor:
        # The mean over the K neighbours: the paper's sum / K, which keeps gradients O(1).
        projected = project(candidates, params, frame)
        return projection_energy(projected, joints_2d, mask).mean(-1)

    params, _ = minimize(energy, start, iterations=iterations)
    with torch.no_grad():
        per_candidate = projection_energy(project(candidates, params, frame), joints_2d, mask)
    return params, per_candidate


def weighted_pca(poses: torch.Tensor, weights: torch.Tensor, components: int):
    """poses: (B, K, 14, 3); weights: (B, K) >= 0. Returns mean (B, 42), basis (B, C, 42) with
    orthonormal rows ordered by weighted variance, and the standard deviation along each (B, C)
    mm; C = min(components, K, 42)."""
    flat = poses.flatten(-2)
    w = weights / weights.sum(-1, keepdim=True).clamp_min(1e-12)
    mean = (w[..., None] * flat).sum(-2)
    centred = (flat - mean[..., None, :]) * w.sqrt()[..., None]
    _, sigma, vh = torch.linalg.svd(centred, full_matrices=False)
    c = min(components, vh.shape[-2])
    return mean, vh[..., :c, :], sigma[..., :c]


@dataclass(frozen=True)
class EnergyWeights:
    """omega_p, omega_r, omega_a of eq:energyMin (the paper's values)."""

    projection: float = 0.55
    retrieval: float = 0.35
    anthropometric: float = 0.065


def fit_pose(
    neighbours: torch.Tensor,
    weights: torch.Tensor,
    params: torch.Tensor,
    joints_2d: torch.Tensor,
    mask: torch.Tensor,
    frame: CameraFrame,
    omega: EnergyWeights = EnergyWeights(),
    components: int = 18,
    iterations: int = 30,
) -> torch.Tensor:
    """eq:energyMin2 for B problems.

    neighbours: (B, K, 14, 3) mm camera-oriented; weights: (B, K) in [0, 1]; params: (B, 6) the
    chosen projection (fixed); joints_2d: (B, 14, 2) px; mask: (B, 14) float, the joints E_p uses.
    Returns the pose (B, 14, 3) mm in the neighbours' orientation.
    """
    mean, basis, sigma = weighted_pca(neighbours, weights, components)
    # Coefficients in standard deviations: every direction has the same scale for L-BFGS.
    scaled_basis = basis * sigma.clamp_min(1e-3)[..., None]
    neighbour_vectors = neighbours.flatten(-2)  # constant: computed once, not per evaluation
    neighbour_limbs = limb_lengths(neighbours)

    def pose_of(coefficients: torch.Tensor) -> torch.Tensor:
        return (mean + (coefficients[:, None, :] @ scaled_basis)[:, 0]).reshape(-1, 14, 3)

    def energy(coefficients: torch.Tensor) -> torch.Tensor:
        pose = pose_of(coefficients)[:, None]  # (B, 1, 14, 3)
        e_p = projection_energy(project(pose, params, frame), joints_2d, mask)[:, 0]
        e_r = weighted_robust_distance(pose.flatten(-2), neighbour_vectors, weights)[:, 0]
        e_a = weighted_robust_distance(limb_lengths(pose), neighbour_limbs, weights)[:, 0]
        return omega.projection * e_p + omega.retrieval * e_r + omega.anthropometric * e_a

    start = mean.new_zeros(len(mean), scaled_basis.shape[-2])
    coefficients, _ = minimize(energy, start, iterations=iterations)
    return pose_of(coefficients)
