"""Pictorial structure model (PSM) over the 14-joint tree of ds3d.skeleton (paper, eqt:ps).

    P(x | I)  ∝  prod_i phi_i(x_i | I)  prod_(i,j) phi_ij(x_i, x_j)

The binaries (eq:binary) are, for each limb (child i, parent j), a mixture of C Gaussians over
the offset d_ij = x_i - x_j, weighted by gamma_c = p(c)^alpha (alpha = 0.1), where p(c) is the
frequency of the k-means cluster c:

    phi_ij = max_c gamma_c exp(-0.5 (d_ij - mu_c)^T Sigma_c^-1 (d_ij - mu_c)).

The mixture is maximised over c, not summed, as max-product inference over (x, c) requires, and
the Gaussian is unnormalised, as in eq:binary. Sigma_c is diagonal (per-axis variances): that
keeps the max-convolution separable and exact on the grid (ds3d.image2d.maxconv); k-means with
many clusters leaves each cluster small, so the lost correlation is a second-order effect.

The same `fit_pairwise_mixtures` serves training (B = 1, all annotated poses, C = 15) and the
3D stage (eqt:best_segments_pose: B = batch x joint sets, the projected candidates, C = 5).
`infer` runs max-product from the leaves to the root (the neck) and back-tracks the MAP pose.

Units: joints and mixtures in pixels (x, y); unaries on a grid of `stride` pixels per cell,
cell (u, v) at pixel (u * stride, v * stride).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ds3d.errors import InvalidPose
from ds3d.image2d.maxconv import CHUNK_ELEMENTS, best_child, max_convolve
from ds3d.skeleton import LIMBS, NUM_JOINTS, PARENT

NUM_LIMBS = len(LIMBS)
ROOT = PARENT.index(-1)
_LIMB_CHILD = torch.tensor([i for i, _ in LIMBS])
_LIMB_PARENT = torch.tensor([j for _, j in LIMBS])
_LIMB_OF_CHILD = {i: limb for limb, (i, _) in enumerate(LIMBS)}


def _top_down_order() -> tuple[int, ...]:
    """Non-root joints, every parent before its children (breadth first from the root)."""
    order, frontier = [], [ROOT]
    while frontier:
        frontier = [i for p in frontier for i, q in enumerate(PARENT) if q == p]
        order += frontier
    return tuple(order)


TOP_DOWN = _top_down_order()


@dataclass(frozen=True)
class PairwiseMixtures:
    """The binaries of the PSM: one Gaussian mixture per limb (order of ds3d.skeleton.LIMBS).

    mean: (B, 13, C, 2) offset child - parent, pixels (x, y).
    var: (B, 13, C, 2) per-axis variance of the offset, pixels^2, > 0.
    log_gamma: (B, 13, C) alpha * log p(c); -inf for an empty cluster.
    """

    mean: Tensor
    var: Tensor
    log_gamma: Tensor

    def __post_init__(self):
        b, limbs, c = self.log_gamma.shape
        want = (b, NUM_LIMBS, c, 2)
        if limbs != NUM_LIMBS or self.mean.shape != want or self.var.shape != want:
            raise ValueError(
                f"mixture shapes mean {tuple(self.mean.shape)}, var {tuple(self.var.shape)},"
                f" log_gamma {tuple(self.log_gamma.shape)}; want (B, {NUM_LIMBS}, C, 2|·)"
            )
        if not bool((self.var > 0).all()):
            raise ValueError("mixture variances must be > 0")

    @property
    def batch_size(self) -> int:
        return self.log_gamma.shape[0]

    @property
    def n_components(self) -> int:
        return self.log_gamma.shape[2]

    def to(self, device: torch.device | str) -> PairwiseMixtures:
        return PairwiseMixtures(
            self.mean.to(device), self.var.to(device), self.log_gamma.to(device)
        )

    def state_dict(self) -> dict[str, Tensor]:
        return {"mean": self.mean, "var": self.var, "log_gamma": self.log_gamma}

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor]) -> PairwiseMixtures:
        return cls(state["mean"], state["var"], state["log_gamma"])

    def log_potentials(self, joints_2d: Tensor) -> Tensor:
        """log phi_ij of each limb of given poses. joints_2d: (B, 14, 2) pixels (B may be any
        size when the mixture batch is 1) -> (B, 13), max over components."""
        offset = joints_2d[:, _LIMB_CHILD] - joints_2d[:, _LIMB_PARENT]  # (B, 13, 2)
        diff = offset[:, :, None, :] - self.mean
        return (self.log_gamma - 0.5 * (diff * diff / self.var).sum(-1)).amax(-1)


@dataclass(frozen=True)
class PsmResult:
    """MAP pose of the PSM.

    joints_2d: (B, 14, 2) float32, pixels (x, y) = cell * stride.
    cells: (B, 14, 2) long grid cells (x, y) of the joints.
    score: (B,) MAP log-posterior: sum of the unaries and of the log binaries at the MAP pose.
    joint_scores: (B, 14) the unary log-probability of each joint at its MAP cell.
    """

    joints_2d: Tensor
    cells: Tensor
    score: Tensor
    joint_scores: Tensor


def _kmeans_pp_init(x: Tensor, w: Tensor, k: int, gen: torch.Generator) -> Tensor:
    """Weighted k-means++ seeds. x: (R, N, 2), w: (R, N) >= 0, every row > 0 -> (R, k, 2)."""
    rows = torch.arange(x.shape[0], device=x.device)
    first = torch.multinomial(w, 1, generator=gen)[:, 0]
    centres = [x[rows, first]]
    d2 = ((x - centres[0][:, None]) ** 2).sum(-1)
    for _ in range(1, k):
        p = w * d2
        # all weighted mass already sits on a centre: repeat a point, its cluster stays empty
        p = torch.where(p.sum(1, keepdim=True) > 0, p, w)
        pick = torch.multinomial(p, 1, generator=gen)[:, 0]
        centres.append(x[rows, pick])
        d2 = torch.minimum(d2, ((x - centres[-1][:, None]) ** 2).sum(-1))
    return torch.stack(centres, dim=1)


def _assign(x: Tensor, centres: Tensor) -> Tensor:
    """Nearest centre (first on ties). x: (R, N, 2), centres (R, C, 2) -> (R, N) long."""
    return torch.cdist(x, centres).argmin(-1)


def _cluster_sums(x: Tensor, w: Tensor, label: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Per-cluster weight (R, k) and weighted sum of x (R, k, 2)."""
    mass = torch.zeros(x.shape[0], k, dtype=x.dtype, device=x.device).scatter_add_(1, label, w)
    total = torch.zeros(x.shape[0], k, 2, dtype=x.dtype, device=x.device)
    total.scatter_add_(1, label[..., None].expand(-1, -1, 2), w[..., None] * x)
    return mass, total


def fit_pairwise_mixtures(
    joints_2d: Tensor,
    weights: Tensor | None = None,
    visible: Tensor | None = None,
    n_components: int = 15,
    iterations: int = 20,
    seed: int = 0,
    min_var: float = 1.0,
    alpha: float = 0.1,
) -> PairwiseMixtures:
    """Fit the binaries (eq:binary) of B independent PSMs from N poses each.

    joints_2d: (B, N, 14, 2) pixels (x, y); entries that carry no weight may be non-finite.
    weights: (B, N) >= 0 sample weights (None: all 1); a zero weight leaves the pose out.
    visible: (B, N, 14) bool (None: all visible); a limb's offset counts only when both of its
        joints are visible.
    For each item and limb: weighted k-means (Lloyd, `iterations` steps, k-means++ seeds drawn
    with `seed`) on the offsets child - parent into `n_components` clusters; each cluster gives
    a Gaussian with the weighted mean, the weighted per-axis variance plus `min_var` (pixels^2,
    so that no Gaussian is singular) and log_gamma = alpha * log(cluster weight / total weight).
    Clusters that end empty get log_gamma = -inf. Computed in float64; returns float32.
    Raises InvalidPose for bad shapes or non-finite weighted offsets and ValueError for negative
    or non-finite weights or a limb of an item without any weighted visible sample.
    """
    if joints_2d.ndim != 4 or joints_2d.shape[2:] != (NUM_JOINTS, 2):
        raise InvalidPose(
            f"joints_2d must be (B, N, {NUM_JOINTS}, 2), got {tuple(joints_2d.shape)}"
        )
    b, n = joints_2d.shape[:2]
    device = joints_2d.device
    joints = joints_2d.to(torch.float64)
    w = torch.ones(b, n, dtype=torch.float64, device=device) if weights is None else weights
    if w.shape != (b, n):
        raise ValueError(f"weights must be ({b}, {n}), got {tuple(w.shape)}")
    w = w.to(device=device, dtype=torch.float64)
    if not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
        raise ValueError("weights must be finite and >= 0")
    child, parent = _LIMB_CHILD.to(device), _LIMB_PARENT.to(device)
    w_limb = w[:, :, None].expand(b, n, NUM_LIMBS)
    if visible is not None:
        if visible.shape != (b, n, NUM_JOINTS):
            raise ValueError(
                f"visible must be ({b}, {n}, {NUM_JOINTS}), got {tuple(visible.shape)}"
            )
        visible = visible.to(device=device, dtype=torch.bool)
        w_limb = w_limb * (visible[:, :, child] & visible[:, :, parent])
    offsets = joints[:, :, child] - joints[:, :, parent]  # (B, N, 13, 2)
    used = w_limb > 0
    if not bool(torch.isfinite(offsets)[used].all()):
        raise InvalidPose("non-finite joint coordinates in a weighted, visible limb")
    offsets = torch.where(used[..., None], offsets, torch.zeros_like(offsets))
    # one row per (item, limb)
    x = offsets.permute(0, 2, 1, 3).reshape(b * NUM_LIMBS, n, 2)
    wr = w_limb.permute(0, 2, 1).reshape(b * NUM_LIMBS, n)
    if bool((wr.sum(1) <= 0).any()):
        raise ValueError("a limb of some item has no visible sample with positive weight")

    gen = torch.Generator(device=device).manual_seed(seed)
    centres = _kmeans_pp_init(x, wr, n_components, gen)
    for _ in range(iterations):
        mass, total = _cluster_sums(x, wr, _assign(x, centres), n_components)
        # an empty cluster keeps its centre
        centres = torch.where(
            mass[..., None] > 0, total / mass.clamp_min(1e-300)[..., None], centres
        )
    label = _assign(x, centres)
    mass, total = _cluster_sums(x, wr, label, n_components)
    filled = mass > 0
    mean = torch.where(filled[..., None], total / mass.clamp_min(1e-300)[..., None], centres)
    resid = x - mean.gather(1, label[..., None].expand(-1, -1, 2))
    second = torch.zeros_like(mean).scatter_add_(
        1, label[..., None].expand(-1, -1, 2), wr[..., None] * resid * resid
    )
    var = torch.where(filled[..., None], second / mass.clamp_min(1e-300)[..., None], 0.0) + min_var
    freq = mass / mass.sum(1, keepdim=True)
    log_gamma = torch.where(filled, alpha * torch.log(freq.clamp_min(1e-300)), -torch.inf)
    return PairwiseMixtures(
        mean.reshape(b, NUM_LIMBS, n_components, 2).float(),
        var.reshape(b, NUM_LIMBS, n_components, 2).float(),
        log_gamma.reshape(b, NUM_LIMBS, n_components).float(),
    )


def infer(
    unaries: Tensor,
    mixtures: PairwiseMixtures,
    stride: float | Tensor = 1.0,
    chunk_elements: int = CHUNK_ELEMENTS,
) -> PsmResult:
    """MAP pose of the PSM (eqt:ps) by exact max-product over the tree, batched.

    unaries: (B, 14, H, W) log-probabilities log phi_i on the grid (-inf allowed, no NaN);
        computation runs in their dtype (float32 or float64).
    mixtures: batch size 1 (one model for all items) or B.
    stride: pixels per grid cell, a float or a (B,) tensor; cell (u, v) is pixel
        (u * stride, v * stride), so the mixtures (pixels) become mean / stride and
        var / stride^2 in cells.
    Messages run from the leaves to the root (the neck); the MAP pose is back-tracked from the
    root's best cell. Returns PsmResult (joints in pixels, their cells, the MAP log-posterior and
    the unary at each joint's MAP cell).
    """
    if unaries.ndim != 4 or unaries.shape[1] != NUM_JOINTS:
        raise ValueError(f"unaries must be (B, {NUM_JOINTS}, H, W), got {tuple(unaries.shape)}")
    if bool(torch.isnan(unaries).any()):
        raise ValueError("unaries contain NaN")
    b, _, _, width = unaries.shape
    if mixtures.batch_size not in (1, b):
        raise ValueError(f"mixtures have batch {mixtures.batch_size}, unaries {b}")
    dtype = unaries.dtype if unaries.is_floating_point() else torch.float32
    scale = torch.as_tensor(stride, dtype=dtype, device=unaries.device)
    if scale.ndim == 1 and scale.shape != (b,):
        raise ValueError(f"stride must be a float or ({b},), got {tuple(scale.shape)}")
    scale = scale.reshape(-1, 1, 1, 1)
    mean = mixtures.mean.to(unaries.device, dtype) / scale  # (1|B, 13, C, 2) cells
    var = mixtures.var.to(unaries.device, dtype) / (scale * scale)
    log_gamma = mixtures.log_gamma.to(unaries.device, dtype)
    if log_gamma.shape[0] != mean.shape[0]:
        log_gamma = log_gamma.expand(mean.shape[0], -1, -1)

    beliefs = unaries.to(dtype).clone()  # unary + messages from the children, per joint
    for child in reversed(TOP_DOWN):
        limb = _LIMB_OF_CHILD[child]
        beliefs[:, PARENT[child]] += max_convolve(
            beliefs[:, child], mean[:, limb], var[:, limb], log_gamma[:, limb], chunk_elements
        )
    score, flat = beliefs[:, ROOT].reshape(b, -1).max(dim=1)
    cells = torch.zeros(b, NUM_JOINTS, 2, dtype=torch.long, device=unaries.device)
    cells[:, ROOT, 0], cells[:, ROOT, 1] = flat % width, flat // width
    for child in TOP_DOWN:
        limb = _LIMB_OF_CHILD[child]
        cells[:, child], _ = best_child(
            beliefs[:, child],
            cells[:, PARENT[child]],
            mean[:, limb],
            var[:, limb],
            log_gamma[:, limb],
        )
    joint_scores = (
        unaries.to(dtype).flatten(2).gather(2, (cells[..., 1] * width + cells[..., 0])[..., None])
    )
    joints_2d = cells.to(torch.float32) * scale.reshape(-1, 1, 1).to(torch.float32)
    return PsmResult(joints_2d, cells, score, joint_scores[..., 0])
