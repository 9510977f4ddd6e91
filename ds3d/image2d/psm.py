"""Pictorial structure model (PSM) over the 14-joint tree of ds3d.skeleton (paper, eqt:ps).

    P(x | I)  ∝  prod_i phi_i(x_i | I)  prod_(i,j) phi_ij(x_i, x_j)

The binaries (eq:binary) are, for each limb (child i, parent j), a mixture of C Gaussians over
the offset d_ij = x_i - x_j, weighted by gamma_c = p(c)^alpha (alpha = 0.1), where p(c) is the
frequency of the k-means cluster c:

    phi_ij = max_c gamma_c exp(-0.5 (d_ij - mu_c)^T Sigma_c^-1 (d_ij - mu_c)).

The mixture is maximised over c, not summed, as max-product inference over (x, c) requires, and
the Gaussian is unnormalised, as in eq:binary. Sigma_c is diagonal (per-axis variances): that
keeps the max-convolution separable and exact on the grid (ds3d.image2d.maxconv). Within the
small k-means clusters the correlation hardly matters: with the same clusters fit on LSPet (and
mirrors), the mean log-density of held-out LSP-train limb offsets was -7.986 (diagonal) vs
-7.992 (full) nats at C = 15, and -8.019 vs -8.004 at C = 5.

The same `fit_pairwise_mixtures` serves training (B = 1, all annotated poses, C = 3) and the
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
from ds3d.image2d.maxconv import best_child, max_convolve
from ds3d.skeleton import LIMBS, NUM_JOINTS, PARENT

NUM_LIMBS = len(LIMBS)
ROOT = PARENT.index(-1)
_LIMB_CHILD = torch.tensor([i for i, _ in LIMBS])
_LIMB_PARENT = torch.tensor([j for _, j in LIMBS])
_LIMB_OF_CHILD = {i: limb for limb, (i, _) in enumerate(LIMBS)}


def _tree_levels() -> tuple[tuple[int, ...], ...]:
    """Non-root joints by depth below the root (breadth first): level 0 = the root's children.
    The joints of one level are independent given the levels above, so each level's messages
    (and back-tracking steps) run as one batched call."""
    levels, frontier = [], [ROOT]
    while frontier:
        frontier = [i for p in frontier for i, q in enumerate(PARENT) if q == p]
        levels.append(tuple(frontier))
    return tuple(level for level in levels if level)


LEVELS = _tree_levels()

# What one more PSM call costs, in the units of its maps' cost (h * w * max(h, w) cells, the
# max-convolution's candidates; ds3d.util.groups.padded_groups): a call's fixed ops took about
# 5 ms on one thread of the 2-core machine, a 64 x 64 map about 18 ms more (docs/tuning.md).
PSM_CALL_COST = 40_000


def no_joint_beyond(maps: Tensor, height: int, width: int) -> Tensor:
    """Unaries (..., h, w) padded to (..., height, width) below and right with -inf, cells
    where no joint can go: a PSM on the padded maps answers as on the maps alone."""
    pad = (0, width - maps.shape[-1], 0, height - maps.shape[-2])
    return torch.nn.functional.pad(maps, pad, value=-torch.inf)


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

    def typical_lengths(self) -> Tensor:
        """(13,) px at the working scale: each limb's typical length, the median over its
        components of the length of their mean offset (of the first batch element)."""
        return self.mean[0].norm(dim=-1).median(dim=-1).values

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
    score: (B,) unnormalised MAP log-posterior: the sum of the unaries and of the log binaries
        at the MAP pose, in the dtype of the unaries.
    joint_scores: (B, 14) the unary log-probability of each joint at its MAP cell (not a
        max-marginal), in the dtype of the unaries.
    """

    joints_2d: Tensor
    cells: Tensor
    score: Tensor
    joint_scores: Tensor


def _sample(p: Tensor, u: Tensor) -> Tensor:
    """One index per row drawn with probability proportional to p (R, N) >= 0, given uniform
    numbers u (R,) in [0, 1) -> (R,) long. Inverse-CDF sampling: much faster than
    torch.multinomial for many short rows."""
    cdf = p.cumsum(1)
    idx = torch.searchsorted(cdf, u[:, None].to(p.dtype) * cdf[:, -1:], right=True)[:, 0]
    return idx.clamp_max(p.shape[1] - 1)


def _sq_dist(xs: Tensor, ys: Tensor, centre: Tensor) -> Tensor:
    """xs, ys: (R, N), centre: (R, 2) -> (R, N) squared distances."""
    dx = xs - centre[:, 0, None]
    dy = ys - centre[:, 1, None]
    return dx * dx + dy * dy


def _kmeans_pp_init(xs: Tensor, ys: Tensor, w: Tensor, k: int, seed: int) -> Tensor:
    """Weighted k-means++ seeds. xs, ys, w: (R, N) with R = items x 13 limbs (limb fastest),
    w >= 0 with every row > 0 -> (R, k, 2). Every item draws the same uniform numbers, so an
    item's mixture does not depend on the batch it comes in."""
    gen = torch.Generator().manual_seed(seed)
    uniforms = torch.rand(k, NUM_LIMBS, generator=gen, dtype=torch.float64).to(xs.device)
    uniforms = uniforms.repeat(1, xs.shape[0] // NUM_LIMBS)  # (k, R)
    points = torch.stack((xs, ys), dim=2)  # (R, N, 2)
    rows = torch.arange(xs.shape[0], device=xs.device)
    centres = [points[rows, _sample(w, uniforms[0])]]
    d2 = _sq_dist(xs, ys, centres[0])
    for step in range(1, k):
        p = w * d2
        # all weighted mass already sits on a centre: repeat a point, its cluster stays empty
        p = torch.where(p.sum(1, keepdim=True) > 0, p, w)
        centres.append(points[rows, _sample(p, uniforms[step])])
        d2 = torch.minimum(d2, _sq_dist(xs, ys, centres[-1]))
    return torch.stack(centres, dim=1)


def _assign(xs: Tensor, ys: Tensor, centres: Tensor) -> Tensor:
    """Nearest centre, the first on ties. xs, ys: (R, N), centres (R, C, 2) -> (R, N) long.
    A loop over the few centres: argmin over a short axis is several times slower on CPU."""
    best = _sq_dist(xs, ys, centres[:, 0])
    label = torch.zeros_like(best, dtype=torch.int32)  # int32: faster to fill than int64
    for c in range(1, centres.shape[1]):
        d2 = _sq_dist(xs, ys, centres[:, c])
        label.masked_fill_(d2 < best, c)
        best = torch.minimum(d2, best)
    return label.long()


def _cluster_sums(values: Tensor, label: Tensor, k: int) -> Tensor:
    """Per-cluster sums. values: (D, R, N), label: (R, N) -> (R, k, D)."""
    d, r, _ = values.shape
    out = torch.zeros(d, r, k, dtype=values.dtype, device=values.device)
    return out.scatter_add_(2, label.expand(d, -1, -1), values).permute(1, 2, 0)


def _weighted_kmeans(
    xs: Tensor, ys: Tensor, w: Tensor, k: int, iterations: int, seed: int
) -> Tensor:
    """Lloyd's algorithm on R independent weighted 2D point sets, all rows at once.
    xs, ys, w: (R, N) -> labels (R, N) long in [0, k). Stops early once no label changes."""
    centres = _kmeans_pp_init(xs, ys, w, k, seed)
    label = _assign(xs, ys, centres)
    weighted = torch.stack((w, w * xs, w * ys))
    for _ in range(iterations):
        sums = _cluster_sums(weighted, label, k)
        mass = sums[..., :1]
        # an empty cluster keeps its centre
        centres = torch.where(mass > 0, sums[..., 1:] / mass.clamp_min(1e-30), centres)
        new_label = _assign(xs, ys, centres)
        if torch.equal(new_label, label):
            break
        label = new_label
    return label


def fit_pairwise_mixtures(
    joints_2d: Tensor,
    weights: Tensor | None = None,
    *,
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
    a Gaussian with the weighted mean, the weighted per-axis variance plus `min_var` (> 0,
    pixels^2, so that no Gaussian is singular) and
    log_gamma = alpha * log(cluster weight / total weight).
    Clusters that end empty get log_gamma = -inf (their mean is 0). Returns float32.
    Raises InvalidPose for bad shapes or non-finite weighted offsets and ValueError for negative
    or non-finite weights or a limb of an item without any weighted visible sample.
    """
    if joints_2d.ndim != 4 or joints_2d.shape[2:] != (NUM_JOINTS, 2):
        raise InvalidPose(
            f"joints_2d must be (B, N, {NUM_JOINTS}, 2), got {tuple(joints_2d.shape)}"
        )
    if not min_var > 0:
        raise ValueError(f"min_var must be > 0, got {min_var}")
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
    x64 = offsets.permute(3, 0, 2, 1).reshape(2, b * NUM_LIMBS, n)  # (2, R, N)
    wr = w_limb.permute(0, 2, 1).reshape(b * NUM_LIMBS, n)
    if bool((wr.sum(1) <= 0).any()):
        raise ValueError("a limb of some item has no visible sample with positive weight")

    # clustering in float32 (2x faster than float64 here); the moments below in float64
    x32 = x64.float()
    label = _weighted_kmeans(x32[0], x32[1], wr.float(), n_components, iterations, seed)
    sums = _cluster_sums(torch.cat((wr[None], wr[None] * x64)), label, n_components)
    mass = sums[..., 0]
    filled = mass > 0
    mean = sums[..., 1:] / mass.clamp_min(1e-300)[..., None]  # (R, C, 2)
    resid = x64 - mean.permute(2, 0, 1).gather(2, label.expand(2, -1, -1))
    second = _cluster_sums(wr[None] * resid * resid, label, n_components)
    var = second / mass.clamp_min(1e-300)[..., None] + min_var
    freq = mass / mass.sum(1, keepdim=True)
    log_gamma = torch.where(filled, alpha * torch.log(freq.clamp_min(1e-300)), -torch.inf)
    return PairwiseMixtures(
        mean.reshape(b, NUM_LIMBS, n_components, 2).float(),
        var.reshape(b, NUM_LIMBS, n_components, 2).float(),
        log_gamma.reshape(b, NUM_LIMBS, n_components).float(),
    )


def local_centroid(unaries: Tensor, cells: Tensor, radius: int, sharpness: float) -> Tensor:
    """Sub-cell joint positions: per joint, the centroid of the unary probabilities raised to
    `sharpness` over the grid cells within `radius` cells of its cell (a disc,
    dx^2 + dy^2 <= radius^2 + radius; cells off the grid weigh nothing).

    The PSM's MAP lies on the grid; its cells are a stride apart (3 px at the working scale,
    against a PCK@0.2 radius of about 6 px there), and the binaries may hold a joint a cell or
    two off its unary peak. The centroid moves it within the disc towards the unary mass.
    unaries: (B, 14, H, W) log-probabilities; cells: (B, 14, 2) long (x, y) on their grid
    -> (B, 14, 2) float32 cells (x, y).
    """
    height, width = unaries.shape[-2:]
    r = torch.arange(-radius, radius + 1, device=cells.device)
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    disc = dx * dx + dy * dy <= radius * radius + radius
    offsets = torch.stack((dx[disc], dy[disc]), dim=-1)  # (K, 2) (x, y)
    around = cells[:, :, None, :] + offsets  # (B, 14, K, 2)
    x, y = around.unbind(-1)
    on_grid = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    flat = (y.clamp(0, height - 1) * width + x.clamp(0, width - 1)).flatten(2)  # (B, 14, K)
    logp = unaries.flatten(2).gather(2, flat).float() * sharpness
    # never all masked: the joint's own cell lies on the grid
    weight = torch.softmax(logp.masked_fill(~on_grid, -torch.inf), dim=-1)
    return (weight[..., None] * around.float()).sum(2)


def infer(
    unaries: Tensor,
    mixtures: PairwiseMixtures,
    stride: float | Tensor = 1.0,
    *,
    chunk_elements: int | None = None,
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
    messages = RootScores(unaries, mixtures, stride, chunk_elements=chunk_elements)
    root = messages.root  # (B, H, W)
    score, flat = root.flatten(1).max(dim=1)
    width = root.shape[-1]
    result = messages.poses(torch.stack((flat % width, flat // width), -1)[:, None])
    return PsmResult(result.joints_2d[:, 0], result.cells[:, 0], score, result.joint_scores[:, 0])


class RootScores:
    """The upward pass of `infer` (arguments as there): `root` (B, H, W), each cell's score of
    the best pose with its root (the neck) there, unary + best children, in the unaries' dtype.
    As a map over positions (and, across a pyramid, scales) it is a detector of people: each
    local maximum is one (the articulated-pose detectors of the PSM literature). `poses` back-
    tracks the best pose below any root cells."""

    def __init__(
        self,
        unaries: Tensor,
        mixtures: PairwiseMixtures,
        stride: float | Tensor = 1.0,
        *,
        chunk_elements: int | None = None,
    ):
        if unaries.ndim != 4 or unaries.shape[1] != NUM_JOINTS or unaries.numel() == 0:
            raise ValueError(f"unaries must be (B, {NUM_JOINTS}, H, W), got {tuple(unaries.shape)}")
        if bool(torch.isnan(unaries).any()):
            raise ValueError("unaries contain NaN")
        b = unaries.shape[0]
        if mixtures.batch_size not in (1, b):
            raise ValueError(f"mixtures have batch {mixtures.batch_size}, unaries {b}")
        dtype = unaries.dtype if unaries.is_floating_point() else torch.float32
        scale = torch.as_tensor(stride, dtype=dtype, device=unaries.device)
        if scale.ndim == 1 and scale.shape != (b,):
            raise ValueError(f"stride must be a float or ({b},), got {tuple(scale.shape)}")
        self.scale = scale = scale.reshape(-1, 1, 1, 1)
        mean = mixtures.mean.to(unaries.device, dtype) / scale  # (1|B, 13, C, 2) cells
        var = mixtures.var.to(unaries.device, dtype) / (scale * scale)
        log_gamma = mixtures.log_gamma.to(unaries.device, dtype)
        if log_gamma.shape[0] != mean.shape[0]:
            log_gamma = log_gamma.expand(mean.shape[0], -1, -1)
        self.unaries = unaries.to(dtype)
        # unary + messages from the children, per joint
        self.beliefs = beliefs = self.unaries.clone()
        # Each level's limb mixtures, used by the upward pass and again by the back-tracking.
        self.mixture = {
            level: (
                _per_map(mean, level, b),
                _per_map(var, level, b),
                _per_map(log_gamma, level, b),
            )
            for level in LEVELS
        }
        for level in reversed(LEVELS):
            messages = max_convolve(
                _level_maps(beliefs, level), *self.mixture[level], chunk_elements
            )
            messages = messages.view(b, len(level), *beliefs.shape[2:])
            # In reverse order, as a loop over the children one at a time adds them: the same sums.
            for k in reversed(range(len(level))):
                beliefs[:, PARENT[level[k]]] += messages[:, k]
        self.root = beliefs[:, ROOT]

    def poses(self, roots: Tensor) -> PsmResult:
        """The best pose below each of K root cells per item: roots (B, K, 2) long (x, y).
        Returns PsmResult with a K axis: joints_2d, cells (B, K, 14, 2), score (B, K) the root's
        score, joint_scores (B, K, 14)."""
        b, k = roots.shape[:2]
        height, width = self.root.shape[1:]
        cells = roots.new_zeros(b, k, NUM_JOINTS, 2)
        cells[:, :, ROOT] = roots
        for level in LEVELS:
            parents = cells[:, :, [PARENT[child] for child in level]]  # (B, K, L, 2)
            maps = _level_maps(self.beliefs, level).view(b, 1, len(level), height, width)
            mixture = (t.view(b, 1, len(level), *t.shape[1:]) for t in self.mixture[level])
            best, _ = best_child(
                maps.expand(b, k, -1, -1, -1).reshape(-1, height, width),
                parents.reshape(-1, 2),
                *(t.expand(b, k, *t.shape[2:]).reshape(-1, *t.shape[3:]) for t in mixture),
            )
            cells[:, :, list(level)] = best.view(b, k, len(level), 2)
        at = (cells[..., 1] * width + cells[..., 0]).transpose(1, 2)  # (B, 14, K)
        joint_scores = self.unaries.flatten(2).gather(2, at).transpose(1, 2)
        score = self.root.flatten(1).gather(1, roots[..., 1] * width + roots[..., 0])
        joints_2d = cells.to(torch.float32) * self.scale.reshape(-1, 1, 1, 1).to(torch.float32)
        return PsmResult(joints_2d, cells, score, joint_scores)


def _per_map(t: Tensor, level: tuple[int, ...], b: int) -> Tensor:
    """(1|B, 13, ...) mixture parameters -> (B * len(level), ...) for a level's maps."""
    t = t[:, [_LIMB_OF_CHILD[child] for child in level]]
    return t.expand(b, *t.shape[1:]).reshape(b * len(level), *t.shape[2:])


def _level_maps(beliefs: Tensor, level: tuple[int, ...]) -> Tensor:
    """(B, 14, H, W) -> (B * len(level), H, W): the maps of a level's joints."""
    return beliefs[:, list(level)].reshape(-1, *beliefs.shape[2:])
