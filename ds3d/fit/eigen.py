"""Eigen-decomposition of a batch of small symmetric matrices (the 3D fit's per-problem PCA,
ds3d.fit.solve.weighted_pca), on whatever device they live.

On the CPU, LAPACK's `torch.linalg.eigh`. Elsewhere, a cyclic Jacobi method written in batched
torch ops (`jacobi_eigh`): on CUDA, `eigh` of a batch of 42 x 42 matrices runs cuSOLVER's Jacobi
kernels a handful of launches per matrix, which made it 98.8 % of the lifter's GPU time and most
of its kernel launches (an H200, batch 1,024: ../shared/measurements' torch profile). The method
here is one set of launches for the whole batch, whatever its size.

The Jacobi method (Golub and Van Loan, 8.5): each rotation zeroes one off-diagonal pair; the n/2
rotations of a round touch disjoint pairs, so a round is one batched update of all of them, and
the n - 1 rounds of a round-robin tournament (every pair meets once) make a sweep. Convergence
is quadratic once the off-diagonal mass is small (SWEEPS).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

# Sweeps of jacobi_eigh. The 3D fit's scatters span a wide range of variances, and the smallest
# of its 20 components settle last: lifting 512 poses of Human3.6M S11 with the Jacobi method
# rather than LAPACK moved joints by up to 214, 137, 36, 12 and 0.13 mm after 3, 4, 5, 6 and 8
# sweeps (tests/test_lifter.py holds 8 within 1 mm).
SWEEPS = 8


def symmetric_eigh(matrices: Tensor) -> tuple[Tensor, Tensor]:
    """Eigenvalues (..., n) ascending and eigenvectors (..., n, n) (columns) of symmetric
    matrices (..., n, n), as torch.linalg.eigh: LAPACK on the CPU, jacobi_eigh elsewhere."""
    if matrices.is_cpu:
        return torch.linalg.eigh(matrices)
    return jacobi_eigh(matrices)


def jacobi_eigh(matrices: Tensor, sweeps: int = SWEEPS) -> tuple[Tensor, Tensor]:
    """symmetric_eigh by `sweeps` sweeps of the parallel cyclic Jacobi method (module
    docstring), in the matrices' dtype and on their device. matrices (..., n, n) symmetric ->
    eigenvalues (..., n) ascending, eigenvectors (..., n, n) orthonormal columns."""
    *batch, n, _ = matrices.shape
    a = matrices.reshape(-1, n, n)
    if n % 2:  # a zero row and column: an index every rotation leaves alone, dropped at the end
        a = torch.nn.functional.pad(a, (0, 1, 0, 1))
    size = a.shape[-1]
    half = size // 2
    # Column k of `a` and `vectors` is the original index layout[k]. Each round's move permutes
    # the columns so that the round's pairs are (k, k + half); the rounds are cyclic, so the
    # layout starts as the last round's, as if a sweep had just ended.
    moves, last = _schedule(size)
    moves, last = moves.to(a.device), last.to(a.device)
    a = a.index_select(1, last).index_select(2, last)
    vectors = torch.eye(size, dtype=a.dtype, device=a.device)[:, last].expand_as(a)
    for _ in range(sweeps):
        for move in moves:
            a = a.index_select(1, move).index_select(2, move)
            vectors = vectors.index_select(2, move)
            c, s = _rotation(a, half)
            a = _rotate(_rotate(a, c[..., :, None], s[..., :, None], 1), c[:, None], s[:, None], 2)
            vectors = _rotate(vectors, c[:, None], s[:, None], 2)
    values = torch.diagonal(a, dim1=1, dim2=2)
    if n % 2:
        keep = last < n
        values, vectors = values[:, keep], vectors[:, :n][:, :, keep]
    values, order = values.sort(-1)
    vectors = vectors.gather(2, order[:, None].expand_as(vectors))
    return values.reshape(*batch, n), vectors.reshape(*batch, n, n)


def _rotation(a: Tensor, half: int) -> tuple[Tensor, Tensor]:
    """The Jacobi rotation (c, s) (B, half) of each pair (k, k + half) of a (B, 2 half, 2 half):
    the one that zeroes a[k, k + half] (Golub and Van Loan's sym.schur2)."""
    diagonal = torch.diagonal(a, dim1=1, dim2=2)
    app, aqq = diagonal[:, :half], diagonal[:, half:]
    apq = torch.diagonal(a[:, :half, half:], dim1=1, dim2=2)
    turning = apq != 0
    tau = (aqq - app) / (2 * torch.where(turning, apq, 1))
    sign = torch.where(tau >= 0, 1.0, -1.0).to(a.dtype)
    t = torch.where(turning, sign / (tau.abs() + torch.sqrt(1 + tau * tau)), 0)
    c = torch.rsqrt(1 + t * t)
    return c, t * c


def _rotate(x: Tensor, c: Tensor, s: Tensor, dim: int) -> Tensor:
    """x's rows (dim 1) or columns (dim 2) k and k + half rotated: (c x_k - s x_q, s x_k + c
    x_q), c and s broadcasting against either half."""
    first, second = x.chunk(2, dim)
    return torch.cat((c * first - s * second, s * first + c * second), dim)


@functools.cache
def _schedule(size: int) -> tuple[Tensor, Tensor]:
    """The rounds of a round-robin tournament of `size` (even) indices (every pair meets once),
    as (moves (size - 1, size) long, last (size,) long). Round r puts its pairs at columns
    (k, k + half) in the order order_r; moves[r] is the permutation of the columns from
    order_{r-1} to order_r, cyclically (moves[0] from the last round's), and last is that last
    order: original index of each column."""
    half = size // 2
    players = list(range(size))
    orders = []
    for _ in range(size - 1):
        # players[k] meets players[size - 1 - k]
        orders.append(players[:half] + players[size - 1 : half - 1 : -1])
        players = [players[0], players[-1], *players[1:-1]]
    moves = []
    for before, order in zip([orders[-1], *orders[:-1]], orders, strict=True):
        position = {label: k for k, label in enumerate(before)}
        moves.append([position[label] for label in order])
    return torch.tensor(moves), torch.tensor(orders[-1])
