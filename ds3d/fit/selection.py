"""Discrete choices of the paper: which neighbours to keep and how to weight them (eq:wt,
eq:wtn), and which joint set explains the 2D pose best (eq:energyS)."""

from __future__ import annotations

import torch

from ds3d.fit.energy import limb_energy, retrieval_energy
from ds3d.fit.solve import EnergyWeights


def top_weighted(scores: torch.Tensor, keep: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep the `keep` highest-scoring neighbours and min-max normalise their scores (eq:wtn).

    scores: (..., K), higher = more consistent with the image (eq:wt: summed unaries; without an
    image, the negative 2D fit residual). Returns indices (..., keep) into K and weights
    (..., keep) in [0, 1] (the best is 1, the worst kept is 0; all 1 when they tie).
    """
    top, index = scores.topk(min(keep, scores.shape[-1]), dim=-1)
    low = top.amin(-1, keepdim=True)
    span = top.amax(-1, keepdim=True) - low
    weights = torch.where(span > 0, (top - low) / span.clamp_min(1e-12), 1.0)
    return index, weights


def set_energy(
    candidates: torch.Tensor,
    weights: torch.Tensor,
    projection_energies: torch.Tensor,
    omega: EnergyWeights = EnergyWeights(),
) -> torch.Tensor:
    """eq:energyS, as a mean over the K neighbours (the same argmin as the paper's sum):
    E(X^k, M_s, s) of each neighbour, judged by its own projection error and its distance to
    the other (weighted) neighbours.

    candidates: (..., K, 14, 3) mm; weights: (..., K); projection_energies: (..., K) E_p of each
    neighbour under the set's fitted projection. Returns (...,), lower is better.
    """
    e_r = retrieval_energy(candidates, candidates, weights)
    e_a = limb_energy(candidates, candidates, weights)
    total = omega.projection * projection_energies + omega.retrieval * e_r
    return (total + omega.anthropometric * e_a).mean(-1)
