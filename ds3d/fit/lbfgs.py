"""Batched L-BFGS: many small independent problems minimised together in one set of tensor ops.

torch.optim.LBFGS minimises one scalar; summing B independent energies into that scalar would
share a single step length (and curvature history) across all problems, so an easy problem
waits for a hard one and vice versa. Here every problem keeps its own history and its own
backtracking (Armijo) line search; only the tensor ops are shared.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

Energy = Callable[[torch.Tensor], torch.Tensor]


def _value_and_grad(energy: Energy, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        value = energy(x)
        (grad,) = torch.autograd.grad(value.sum(), x)
    return value.detach(), grad


def _direction(grad, steps, changes, rho, newest) -> torch.Tensor:
    """Two-loop recursion, batched. steps, changes: (B, m, n); rho: (B, m), 0 = unused slot."""
    m = steps.shape[1]
    order = [(newest - i) % m for i in range(m)]  # newest first
    q = -grad
    alphas = {}
    for j in order:
        alphas[j] = rho[:, j] * (steps[:, j] * q).sum(-1)
        q = q - alphas[j][:, None] * changes[:, j]
    s, y = steps[:, newest], changes[:, newest]
    yy = (y * y).sum(-1)
    gamma = torch.where(rho[:, newest] > 0, (s * y).sum(-1) / yy.clamp_min(1e-20), 1.0)
    r = gamma[:, None] * q
    for j in reversed(order):
        beta = rho[:, j] * (changes[:, j] * r).sum(-1)
        r = r + (alphas[j] - beta)[:, None] * steps[:, j]
    return r


def minimize(
    energy: Energy,
    x0: torch.Tensor,
    iterations: int = 20,
    history: int = 8,
    max_halvings: int = 10,
    armijo: float = 1e-4,
    tolerance: float = 1e-5,
    relative_decrease: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Minimise B independent energies.

    energy: maps x (B, n) to (B,) energies; it must not mix problems (row b of the output may
    depend only on row b of x). x0: (B, n) starting points. Returns (x, energy(x)), both detached.
    A problem stops when its gradient's largest entry falls below `tolerance`, when a step
    lowers its energy by less than `relative_decrease` of its value, or when its line search finds
    no decrease (converged to float precision); the energy never increases.
    """
    x = x0.detach().clone()
    value, grad = _value_and_grad(energy, x)
    batch, dim = x.shape
    steps = x.new_zeros(batch, history, dim)
    changes = x.new_zeros(batch, history, dim)
    rho = x.new_zeros(batch, history)
    newest = history - 1
    active = grad.abs().amax(-1) > tolerance
    for _ in range(iterations):
        if not bool(active.any()):
            break
        direction = _direction(grad, steps, changes, rho, newest)
        slope = (direction * grad).sum(-1)
        uphill = slope >= 0  # history gone stale: fall back to steepest descent
        direction = torch.where(uphill[:, None], -grad, direction)
        slope = torch.where(uphill, -(grad * grad).sum(-1), slope)
        first = (rho > 0).sum(-1) == 0
        # Without curvature information, a unit step along -grad has no scale: start small.
        step = torch.where(first, (1.0 / grad.abs().sum(-1).clamp_min(1e-12)).clamp_max(1.0), 1.0)
        accepted = torch.zeros(batch, dtype=torch.bool, device=x.device)
        new_x = x.clone()
        for _ in range(max_halvings):
            trial = x + step[:, None] * direction
            with torch.no_grad():
                trial_value = energy(trial)
            ok = active & ~accepted & (trial_value <= value + armijo * step * slope)
            new_x = torch.where(ok[:, None], trial, new_x)
            accepted |= ok
            if bool((accepted | ~active).all()):
                break
            step = torch.where(accepted, step, step / 2)
        active &= accepted
        if not bool(active.any()):
            break
        new_value, new_grad = _value_and_grad(energy, new_x)
        s, y = new_x - x, new_grad - grad
        sy = (s * y).sum(-1)
        newest = (newest + 1) % history
        good = accepted & (sy > 1e-10)
        steps[:, newest] = torch.where(good[:, None], s, 0.0)
        changes[:, newest] = torch.where(good[:, None], y, 0.0)
        rho[:, newest] = torch.where(good, 1.0 / sy.clamp_min(1e-10), 0.0)
        progress = value - new_value > relative_decrease * value.abs()
        x = torch.where(accepted[:, None], new_x, x)
        value = torch.where(accepted, new_value, value)
        grad = torch.where(accepted[:, None], new_grad, grad)
        active &= progress & (grad.abs().amax(-1) > tolerance)
    return x.detach(), value.detach()
