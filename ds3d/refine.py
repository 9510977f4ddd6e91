"""The 2D refinement of the paper's 3D stage (eqt:best_segments_pose): per image and joint set, a
PSM whose unaries are the 2D stage's and whose binaries are fit to the projections of the set's
weighted 3D neighbours; and the conversions between image pixels and the unary grid's cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import (
    PSM_CALL_COST,
    PairwiseMixtures,
    fit_pairwise_mixtures,
    infer,
    no_joint_beyond,
)
from ds3d.image2d.result import LOG_EPS, Estimate2D
from ds3d.skeleton import NUM_JOINTS
from ds3d.util.groups import padded_groups
from ds3d.util.threads import map_on_threads, split_rows


@dataclass(frozen=True)
class RefineParams:
    """components: c of the refinement binaries (the paper: 5). min_var: floor of their per-axis
    variance, in unary cells^2 (one cell is `stride` px at the working scale). window_margin:
    cells of search region around the neighbours' projections (search_window). unary_weight:
    the refinement's unaries relative to the 2D stage's (InferenceParams.unary_weight), against
    the binaries. min_var and unary_weight were chosen on LSP train images held out from the 2D
    model's training (docs/tuning.md)."""

    components: int = 5
    min_var: float = 4.0
    window_margin: int = 4
    unary_weight: float = 1.0
    # The PSMs run on the window max-pooled by this factor (a max-convolution costs the cube of
    # the side); each joint then goes to its pooled block's best cell, then to its local
    # centroid on the full grid (InferenceParams.joint_cells).
    pool: int = 2
    # Lloyd steps of the binaries' k-means (fit_pairwise_mixtures): a batch's rows took 12-20
    # to settle all at once, at the same PCK as 8 or 4 (docs/tuning.md, refinement), and they
    # were half of the refinement's time.
    kmeans_iterations: int = 8


def image_to_cells(points: torch.Tensor, map_to_image: torch.Tensor) -> torch.Tensor:
    """Image px -> unary grid cells (u, v). points: (B, ..., 2); map_to_image: (B, 2, 3), the
    diagonal affine map of Estimate2D. Returns (B, ..., 2) float."""
    shape = (len(points),) + (1,) * (points.ndim - 2) + (2,)
    scale = torch.diagonal(map_to_image[:, :, :2], dim1=1, dim2=2).reshape(shape)
    return (points - map_to_image[:, :, 2].reshape(shape)) / scale


def cells_to_image(cells: torch.Tensor, map_to_image: torch.Tensor) -> torch.Tensor:
    """Unary grid cells (u, v) -> image px; the inverse of image_to_cells. Shapes alike."""
    shape = (len(cells),) + (1,) * (cells.ndim - 2) + (2,)
    scale = torch.diagonal(map_to_image[:, :, :2], dim1=1, dim2=2).reshape(shape)
    return cells * scale + map_to_image[:, :, 2].reshape(shape)


@dataclass
class Refinement:
    """The PSM MAP of every (image, set). joints_2d: (B, S, 14, 2) px of the input image;
    score: (B, S) MAP log-posterior (higher is better)."""

    joints_2d: torch.Tensor
    score: torch.Tensor


def search_window(
    unaries: torch.Tensor, cells: torch.Tensor, margin: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cut one image's unaries down to the cells its neighbours' projections span.

    unaries: (14, h, w); cells: (N, 14, 2) grid cells (u, v); margin: cells added on every
    side. Cells beyond the unary grid read log(LOG_EPS), the 2D stage's own padding value, so
    the window depends on the image alone, not on the batch it was padded into. The window
    stays within `margin` cells of the grid: that bounds the work when projections run far off
    the image (e.g. under wrong intrinsics), where a batch's larger padded grid could then give
    an image a wider window than it gets alone.
    Returns the window (14, H, W) and its origin (2,) long (u, v) in the grid.
    """
    h, w = unaries.shape[-2:]
    bound = torch.tensor([w - 1 + margin, h - 1 + margin], device=cells.device)
    flat = torch.nan_to_num(cells.flatten(0, 1), nan=0.0, posinf=1e6, neginf=-1e6)
    lo = (flat.amin(0).floor().long() - margin).clamp(min=-margin).minimum(bound)  # (2,)
    hi = (flat.amax(0).ceil().long() + margin).minimum(bound).maximum(lo)
    u = torch.arange(int(lo[0]), int(hi[0]) + 1, device=cells.device)
    v = torch.arange(int(lo[1]), int(hi[1]) + 1, device=cells.device)
    window = unaries[:, v.clamp(0, h - 1)[:, None], u.clamp(0, w - 1)[None, :]]
    inside = ((v >= 0) & (v < h))[:, None] & ((u >= 0) & (u < w))[None, :]
    return torch.where(inside, window, float(np.log(LOG_EPS))), lo


def refine(
    estimate: Estimate2D,
    params: EstimatorParams,
    neighbours_2d: torch.Tensor,
    weights: torch.Tensor,
    config: RefineParams,
) -> Refinement:
    """eqt:best_segments_pose for every (image, set): B * S PSM problems.

    params: the 2D stage's; the refinement's unaries are its log-prob unaries
    (estimate.unaries) times params.unary_weight * config.unary_weight against the binaries,
    and its joints go where params.joint_cells puts them; neighbours_2d: (B, S, N, 14, 2) px,
    the projected neighbours of each set;
    weights: (B, S, N) >= 0, their sample weights in the binaries (eq:binary fit on them with
    `config.components` mixtures, all B * S at once). The MAP of an image's S problems is
    searched together, within `config.window_margin` cells of the span of its neighbours
    (search_window): one window per image rather than the batch's padded grid, which cuts the
    cost of the max-convolutions several fold on LSP images. The weight applies after the
    window is cut, so that cells beyond the grid cost as much as the grid's least likely
    cells (weighting first would make them cheaper, and draw weak joints off the image).
    """
    b, s, n = neighbours_2d.shape[:3]
    unary_weight = params.unary_weight * config.unary_weight
    cells = image_to_cells(neighbours_2d.reshape(b, s * n, NUM_JOINTS, 2), estimate.map_to_image)
    windows = [search_window(estimate.unaries[i], cells[i], config.window_margin) for i in range(b)]
    origin = torch.stack([o for _, o in windows])  # (B, 2)
    local = (cells - origin[:, None, None, :]).reshape(b * s, n, NUM_JOINTS, 2)
    pool = config.pool
    mixtures = fit_pairwise_mixtures(
        (local - (pool - 1) / 2) / pool,  # in pooled cells: cell k covers cells pool k ...
        weights.reshape(b * s, n),
        n_components=config.components,
        min_var=config.min_var / pool**2,
        iterations=config.kmeans_iterations,
    )

    def solve(rows: torch.Tensor) -> list[tuple[int, torch.Tensor, torch.Tensor]]:
        """(image, cells (S, 14, 2), score (S,)) of the S problems of each image in rows: the
        images whose windows are of near sizes as one batch (padded_groups, on the pooled
        cells of S problems each), padded with -inf, where no joint can go, so that each
        answers as its own window alone."""
        mine = rows.tolist()
        pooled_sizes = [
            (-(-windows[i][0].shape[-2] // pool), -(-windows[i][0].shape[-1] // pool)) for i in mine
        ]
        out = []
        for group in padded_groups(pooled_sizes, PSM_CALL_COST / s):
            images = [mine[k] for k in group]
            height = max(windows[i][0].shape[-2] for i in images)
            width = max(windows[i][0].shape[-1] for i in images)
            stack = torch.stack([no_joint_beyond(windows[i][0], height, width) for i in images])
            pooled, best = F.max_pool2d(stack, pool, ceil_mode=True, return_indices=True)
            problems = torch.tensor(
                [i * s + k for i in images for k in range(s)], device=stack.device
            )
            binaries = (
                mixtures.mean[problems],
                mixtures.var[problems],
                mixtures.log_gamma[problems],
            )
            res = infer(
                (unary_weight * pooled).repeat_interleave(s, 0), PairwiseMixtures(*binaries), 1.0
            )
            # each joint's pooled cell -> the cell of the window its maximum came from
            at = res.cells[..., 1] * pooled.shape[-1] + res.cells[..., 0]  # (n S, 14)
            flat = best.repeat_interleave(s, 0).flatten(2).gather(2, at[..., None])[..., 0]
            fine = torch.stack([flat % width, flat // width], -1)
            found = params.joint_cells(stack.repeat_interleave(s, 0), fine).view(
                -1, s, NUM_JOINTS, 2
            )
            score = res.score.view(-1, s)
            out += [(i, found[j], score[j]) for j, i in enumerate(images)]
        return out

    # Whole images to parallel threads, each its own window.
    solved = sorted(
        (
            one
            for part in map_on_threads(solve, split_rows(b, estimate.unaries.device))
            for one in part
        ),
        key=lambda one: one[0],
    )
    found = torch.stack([c for _, c, _ in solved]).view(b, s * NUM_JOINTS, 2) + origin[:, None, :]
    joints_2d = cells_to_image(found, estimate.map_to_image).view(b, s, NUM_JOINTS, 2)
    return Refinement(joints_2d, torch.stack([score for _, _, score in solved]))
