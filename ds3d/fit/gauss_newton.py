"""Batched Gauss-Newton for the paper's robust energies: many small problems in one set of ops.

Every energy of the paper is a weighted sum of robust distances, E = sum_t c_t rho(|r_t|^2) with
rho(e) = e^(1/4) (ds3d.fit.energy.robust), plus, for the bone scales, a quadratic prior. rho is
concave, so rho(e) <= rho(e0) + rho'(e0) (e - e0): each step minimises that upper bound, a
least-squares problem with weights c_t rho'(|r_t|^2) (iteratively reweighted least squares),
by one Levenberg-Marquardt step on the residuals' analytic Jacobian. Where the residuals are
linear in the unknowns this is an exact majorise-minimise step and the energy cannot rise; where
they are not (rotations, perspective), a step that raises a problem's energy is refused and that
problem's damping raised. No autograd: a step is a few dozen tensor ops whatever the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import cast

import torch

from ds3d.fit.energy import EPS


@dataclass
class Residuals:
    """One group of T terms per problem (P problems, n unknowns).

    weight: (P, T) >= 0, c_t; value: (P, T, R) the residual vector r_t; jacobian: (P, T, R, n)
    d r_t / d unknowns, or (P, 1, R, n) when every term of the group shares it (the sum over t
    then collapses before the product), or None when only the energy is wanted. robust: the term
    is c_t |r_t|^(1/2) (the paper's fourth root of the squared norm), else c_t |r_t|^2.
    """

    weight: torch.Tensor
    value: torch.Tensor
    jacobian: torch.Tensor | None = None
    robust: bool = True

    @cached_property
    def squared(self) -> torch.Tensor:
        """(P, T) |r_t|^2."""
        return (self.value * self.value).sum(-1)

    def energy(self) -> torch.Tensor:
        """(P,) the group's energy."""
        cost = (self.squared + EPS).pow(0.25) if self.robust else self.squared
        return (self.weight * cost).sum(-1)

    def whitened(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The reweighted least-squares system at the current point as A (P, R', n) and b
        (P, R'), with J^T W J = A^T A and J^T W r = A^T b."""
        jacobian = self.jacobian
        assert jacobian is not None, "the residuals were evaluated without their jacobian"
        if self.robust:  # rho'(e) = e^(-3/4) / 4: the majoriser's weight
            irls = self.weight * 0.25 * (self.squared + EPS).pow(-0.75)
        else:
            irls = self.weight
        if jacobian.shape[1] == 1:  # shared: the weighted residuals sum first
            root = irls.sum(-1).clamp_min(1e-30).sqrt()[:, None]  # (P, 1)
            combined = (irls[..., None] * self.value).sum(1) / root  # (P, R)
            return jacobian[:, 0] * root[..., None], combined
        root = irls.sqrt()[..., None]  # (P, T, 1)
        return (jacobian * root[..., None]).flatten(1, 2), (self.value * root).flatten(1)


Evaluate = Callable[[torch.Tensor, bool], list[Residuals]]
Retract = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def total_energy(groups: list[Residuals]) -> torch.Tensor:
    """(P,) the energy of all groups (there is at least one)."""
    return cast(torch.Tensor, sum(group.energy() for group in groups))


def add(x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """The retraction of unknowns that live in a vector space."""
    return x + step


def minimize(
    evaluate: Evaluate,
    x0: torch.Tensor,
    iterations: int,
    retract: Retract = add,
    damping: float = 1e-4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Minimise P independent energies by reweighted Levenberg-Marquardt.

    evaluate(x, with_jacobian) -> the residual groups at state x (P, d); retract(x, step (P, n))
    -> the state moved by a step in the n unknowns (plain addition unless the state holds,
    say, a rotation matrix). Returns the state and its energy (P,). A problem's energy never
    rises: a refused step leaves it where it was with ten times the damping.
    """
    x = x0
    value, hessian, gradient = _system(evaluate(x, True))
    lam = torch.full_like(value, damping)
    for _ in range(iterations):
        diagonal = hessian.diagonal(dim1=-2, dim2=-1)
        damped = hessian + torch.diag_embed(lam[:, None] * diagonal + 1e-9)
        step, info = torch.linalg.solve_ex(damped, gradient)
        # a singular system (a problem with no data on an unknown) takes no step, not the batch down
        trial = retract(x, -torch.where((info == 0)[:, None], step, 0.0))
        trial_value, trial_hessian, trial_gradient = _system(evaluate(trial, True))
        better = trial_value <= value
        x = _where(better, trial, x)
        value = _where(better, trial_value, value)
        hessian = _where(better, trial_hessian, hessian)
        gradient = _where(better, trial_gradient, gradient)
        lam = torch.where(better, lam * 0.1, lam * 10).clamp(1e-6, 1e4)
    return x, value


def _system(groups: list[Residuals]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The energy (P,) and the normal equations of all groups, J^T W J (P, n, n) and
    J^T W r (P, n), from one product of their stacked whitened systems."""
    systems = [group.whitened() for group in groups]
    a = torch.cat([a for a, _ in systems], 1).transpose(1, 2)  # (P, n, R')
    b = torch.cat([b for _, b in systems], 1)[..., None]  # (P, R', 1)
    return total_energy(groups), a @ a.transpose(1, 2), (a @ b)[..., 0]


def _where(take: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per problem (leading dim), a where `take` (P,) else b."""
    return torch.where(take.view(-1, *[1] * (a.ndim - 1)), a, b)
