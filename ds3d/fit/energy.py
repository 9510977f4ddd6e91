"""The energy terms of the paper (eq:energyControl, eq:energyMotion, eq:energyLimb).

Each term is a robust (fourth-root) distance. Two choices differ from the paper's text, both
measured on the training subjects (docs/RESULTS.md):
- E_p averages the squared residual over the set's joints and rescales to 14 joints, so that
  sets of 6 and of 14 joints are compared on the same footing when the set is chosen
  (eq:energyS); for the set `all` it is exactly the paper's term.
- E_r and E_a are weighted *means* over the neighbours (the paper sums them); with K_w = 64
  neighbours a sum makes E_p two orders of magnitude too small to matter.
"""

from __future__ import annotations

import torch

from ds3d.skeleton import LIMBS, NUM_JOINTS

EPS = 1e-6  # keeps the fourth root differentiable at zero


def robust(squared_sum: torch.Tensor) -> torch.Tensor:
    """(sum of squares)^(1/4), the paper's robust distance."""
    return (squared_sum + EPS).pow(0.25)


def projection_energy(projected: torch.Tensor, joints_2d: torch.Tensor, mask: torch.Tensor):
    """E_p per pose. projected: (..., N, 14, 2) px; joints_2d: (..., 14, 2) px; mask: (..., 14)
    float, 1 for the joints of the set that are visible. Returns (..., N), px^(1/2)."""
    squared = ((projected - joints_2d[..., None, :, :]) ** 2).sum(-1)  # (..., N, 14)
    per_joint = (squared * mask[..., None, :]).sum(-1) / mask.sum(-1, keepdim=True).clamp_min(1)
    return robust(per_joint * NUM_JOINTS)


def normalised_weights(weights: torch.Tensor) -> torch.Tensor:
    """(..., K) non-negative weights -> (..., K) summing to one."""
    return weights / weights.sum(-1, keepdim=True).clamp_min(1e-12)


def weighted_robust_distance(a: torch.Tensor, b: torch.Tensor, weights: torch.Tensor):
    """sum_k w_k robust(||a_m - b_k||^2) for vectors a: (..., M, D), b: (..., K, D), weights
    (..., K) normalised to sum to one. Returns (..., M).

    cdist's distances (by one matrix product where the sets are large) and the weighted sum as a
    second product: set selection pairs every one of K_w neighbours with every other. robust(d^2)
    is sqrt(d) but for its EPS, which only keeps a gradient finite at zero, and none flows here.
    """
    distance = torch.cdist(a, b)  # (..., M, K)
    return (distance.sqrt() @ normalised_weights(weights)[..., None])[..., 0]


def retrieval_energy(poses: torch.Tensor, neighbours: torch.Tensor, weights: torch.Tensor):
    """E_r: closeness to the retrieved poses. poses: (..., M, 14, 3) mm; neighbours:
    (..., K, 14, 3) mm; weights: (..., K). Returns (..., M), mm^(1/2)."""
    return weighted_robust_distance(poses.flatten(-2), neighbours.flatten(-2), weights)


def limb_vectors(poses: torch.Tensor) -> torch.Tensor:
    """(..., 14, 3) mm -> (..., 13, 3) mm, child minus parent, in ds3d.skeleton.LIMBS order."""
    child, parent = zip(*LIMBS, strict=True)
    return poses[..., list(child), :] - poses[..., list(parent), :]


def limb_lengths(poses: torch.Tensor) -> torch.Tensor:
    """(..., 14, 3) mm -> (..., 13) mm, in ds3d.skeleton.LIMBS order."""
    return limb_vectors(poses).norm(dim=-1)


def limb_energy(poses: torch.Tensor, neighbours: torch.Tensor, weights: torch.Tensor):
    """E_a: anthropometric closeness of limb lengths. Shapes as retrieval_energy."""
    return weighted_robust_distance(limb_lengths(poses), limb_lengths(neighbours), weights)
