"""The forest cascade: image channels -> per-layer class probabilities on a grid of every
`stride`-th pixel, for a batch of images zero-padded to one size. Inference and training
(ds3d.training.forests) both run it.

Layer 1 classifies every `stride`-th pixel into 14 joints + background from image channels. Each
later layer (auto-context) splits on the image channels AND on the previous layer's joint
probability maps, read at offsets, which lets it use where the other joints probably are.
Unaries are log(box-blurred probabilities of the last layer).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ds3d.image2d.buckets import bucket
from ds3d.image2d.features import NUM_IMAGE_CHANNELS, box_mean, image_channels, pad_channels
from ds3d.image2d.forest import Forest, predict_proba
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures, infer
from ds3d.image2d.result import LOG_EPS
from ds3d.skeleton import FLIP, NUM_JOINTS


def grid_positions(
    height: int, width: int, stride: int, device: torch.device | str = "cpu"
) -> tuple[torch.Tensor, int, int]:
    """Pixels evaluated on a (height, width) image: (P, 2) int64 (y, x) = (i * stride, j * stride)
    for a (gh, gw) grid, P = gh * gw (row-major), on `device`. Returns (positions, gh, gw)."""
    ys = torch.arange(0, height, stride, device=device)
    xs = torch.arange(0, width, stride, device=device)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([yy.reshape(-1), xx.reshape(-1)], dim=1), len(ys), len(xs)


def context_channels(
    maps: torch.Tensor,
    stride: int,
    height: int,
    width: int,
    sizes: list[tuple[int, int]] | None = None,
) -> torch.Tensor:
    """A layer's joint probability maps on the grid -> full-resolution channels by nearest grid
    cell.

    maps: (B, 14, gh, gw); sizes: None (every image fills height x width) or B (h, w) sizes of
    the images in a zero-padded batch: each image's pixels then read only its own cells, as
    alone -> (B, 14, height, width) float32.
    """
    b, _, gh, gw = maps.shape
    if sizes is None:
        last = [(gh - 1, gw - 1)] * b
    else:
        last = [((h - 1) // stride, (w - 1) // stride) for h, w in sizes]
    iy = torch.div(
        torch.arange(height, device=maps.device) + stride // 2, stride, rounding_mode="floor"
    )
    ix = torch.div(
        torch.arange(width, device=maps.device) + stride // 2, stride, rounding_mode="floor"
    )
    # Two index_selects per image: ~3x faster than one advanced index over the whole batch.
    return torch.stack(
        [
            m.index_select(1, iy.clamp(max=ly)).index_select(2, ix.clamp(max=lx))
            for m, (ly, lx) in zip(maps, last, strict=True)
        ]
    )


def pose_heatmaps(cells: torch.Tensor, height: int, width: int, sigma: float) -> torch.Tensor:
    """One Gaussian bump per joint: cells (B, 14, 2) (x, y) on a height x width grid, sigma in
    cells -> (B, 14, height, width) float32, 1 at each joint's cell."""
    ys = torch.arange(height, dtype=torch.float32, device=cells.device).view(1, 1, -1, 1)
    xs = torch.arange(width, dtype=torch.float32, device=cells.device).view(1, 1, 1, -1)
    dx = xs - cells[..., 0, None, None].float()
    dy = ys - cells[..., 1, None, None].float()
    return torch.exp(-0.5 * (dx * dx + dy * dy) / (sigma * sigma))


def layer_context(
    probs: torch.Tensor, params: EstimatorParams, mixtures: PairwiseMixtures | None
) -> torch.Tensor:
    """What a context layer reads of the layer before it, on the grid: (B, 15, gh, gw) class
    probabilities -> (B, 14, gh, gw) joint maps box-blurred by context_blur, with
    context_pose_sigma followed by (B, 14, gh, gw) heatmaps of the MAP pose of the PSM
    (`mixtures`) on those probabilities' unaries (as the 2D stage weighs them): the trees can
    then split on where the best whole pose puts each joint, not only on each joint's map."""
    maps = box_mean(probs[:, :NUM_JOINTS].float(), params.context_blur)
    if params.context_pose_sigma is None:
        return maps
    if mixtures is None:
        raise ValueError("context_pose_sigma needs the PSM's mixtures")
    unaries = unaries_from_probs(probs.float(), params.unary_blur)
    cells = infer(unaries * params.unary_weight, mixtures, stride=float(params.stride)).cells
    sigma = params.context_pose_sigma / params.stride
    height, width = maps.shape[-2:]
    return torch.cat([maps, pose_heatmaps(cells, height, width, sigma)], dim=1)


def cascade_probs(
    layers: list[Forest],
    channels: torch.Tensor,
    params: EstimatorParams,
    sizes: list[tuple[int, int]] | None = None,
    mixtures: PairwiseMixtures | None = None,
    cells: torch.Tensor | None = None,
) -> list[torch.Tensor]:
    """Run the forest cascade on a batch.

    channels: (B, 12, H, W) from image_channels, zero outside each image;
    sizes: None (every image fills H x W) or B (h, w) sizes of the images in a zero-padded
    batch: context maps are zeroed outside each image, as around a single image in training;
    mixtures: the PSM's, for layer_context with context_pose_sigma;
    cells: None (every cell) or (B, gh, gw) bool, the cells where the forests run (others read
    as zero, like the cells outside an image)
    -> one (B, 15, gh, gw) class-probability map per layer (joints 0-13, background 14), on the
    grid of grid_positions(H, W, stride).
    """
    b, _, h, w = channels.shape
    device = channels.device
    positions, gh, gw = grid_positions(h, w, params.stride, device)
    # In a padded batch, cells outside an image are zeroed: as around a single image.
    inside = None if sizes is None else valid_cells(sizes, h, w, params.stride, device)
    inside_px = None if sizes is None else valid_cells(sizes, h, w, 1, device)
    index = None
    if cells is not None:
        positions, index = cell_positions(cells, params.stride)
    outputs: list[torch.Tensor] = []
    stack = channels
    for i, forest in enumerate(layers):
        if i > 0:
            context = layer_context(outputs[-1], params, mixtures)
            ctx = context_channels(context, params.stride, h, w, sizes)
            if inside_px is not None:
                ctx = ctx * inside_px
            stack = torch.cat([channels, ctx], dim=1)
        probs = predict_proba(forest, pad_channels(stack, forest.radius), positions)
        probs = probs.permute(0, 2, 1)  # (B, 15, P)
        if index is not None:
            probs = probs.new_zeros(b, probs.shape[1], gh * gw).scatter_(
                2, index[:, None].expand_as(probs), probs
            )
        probs = probs.reshape(b, -1, gh, gw)
        outputs.append(probs if inside is None else probs * inside)
    return outputs


def cell_positions(cells: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The pixels of the chosen cells of each image: cells (B, gh, gw) bool on the grid of
    grid_positions(., ., stride) -> (positions (B, P, 2) int64 (y, x) px, index (B, P) int64
    their row-major cells), P the size bucket (ds3d.image2d.buckets) of the most cells any
    image chose (at least 1), so that the traversal's buffers come in a few sizes; an image with
    fewer repeats its first (cell 0 where it chose none), which computes and writes the same
    value again."""
    b, gw = len(cells), cells.shape[2]
    chosen = cells.reshape(b, -1)
    counts = chosen.sum(1)
    n = min(bucket(max(int(counts.max()), 1)), chosen.shape[1])
    order = torch.argsort((~chosen).to(torch.uint8), dim=1, stable=True)[:, :n]  # chosen first
    first = torch.arange(n, device=cells.device)[None] < counts[:, None]
    index = torch.where(first, order, order[:, :1])
    return torch.stack((index // gw * stride, index % gw * stride), -1), index


def forest_cells(net_unaries: torch.Tensor, reach: float) -> torch.Tensor:
    """Where the forests are worth running: the cells where some joint is at least exp(-reach)
    times as likely as at its best cell, by the joint network's unaries (b, 14, gh, gw), log(P +
    LOG_EPS) -> (b, gh, gw) bool. The ratio is of the probabilities above the floor: with it,
    every cell of a broad map would lie within log(peak / LOG_EPS) nats of the best. Elsewhere
    the network already rules every joint out, and the forests' unaries are added to its
    (settle_left_right): what they would say there cannot bring a joint back."""
    probs = (net_unaries.exp() - LOG_EPS).clamp_min(0)
    best = probs.flatten(2).amax(-1)[..., None, None]
    return (probs >= best * math.exp(-reach)).any(1)


def valid_cells(
    sizes: list[tuple[int, int]],
    height: int,
    width: int,
    stride: int,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """(B, 1, gh, gw) bool on `device`: the cells of the grid of grid_positions(height, width,
    stride) that fall inside each image of a zero-padded batch; sizes: B (h, w)."""
    ys = torch.arange(0, height, stride, device=device)
    xs = torch.arange(0, width, stride, device=device)
    rows = torch.stack([ys < h for h, _ in sizes])  # (B, gh)
    cols = torch.stack([xs < w for _, w in sizes])  # (B, gw)
    return (rows[:, :, None] & cols[:, None, :])[:, None]


def unaries_from_probs(probs: torch.Tensor, blur: int) -> torch.Tensor:
    """(B, 15, gh, gw) class probabilities -> (B, 14, gh, gw) log-prob unaries (blurred)."""
    return torch.log(box_mean(probs[:, :NUM_JOINTS], blur) + LOG_EPS)


def group_channels(
    group: list[np.ndarray], timings: dict[str, float], device: torch.device | str = "cpu"
) -> tuple[torch.Tensor, list[tuple[int, int]]]:
    """Images (H_i, W_i, 3) uint8 zero-padded into one batch of channels (b, 12, H, W) on
    `device`, H x W the buckets of their largest height and width (ds3d.image2d.buckets);
    returns them and the images' (h, w) sizes, and adds its seconds to timings["features"]."""
    t0 = time.perf_counter()
    sizes = [image.shape[:2] for image in group]
    height, width = (bucket(max(side)) for side in zip(*sizes, strict=True))
    channels = batch_channels(group, height, width, device)
    timings["features"] += time.perf_counter() - t0
    return channels, sizes


def group_unaries(
    group: list[np.ndarray],
    channels: torch.Tensor,
    layers: list[Forest],
    mixtures: PairwiseMixtures,
    p: EstimatorParams,
    timings: dict[str, float],
    cells: torch.Tensor | None = None,
) -> torch.Tensor:
    """The cascade's unaries of images (H_i, W_i, 3) uint8 from their group_channels; with
    `p.flip_test`, the last layer's probabilities are averaged with those of each image's
    mirror (mirror_on_grid), mapped back. mixtures: the PSM's, for layer_context; cells: as
    cascade_probs (the same cells of the mirrors are read).

    Returns (b, 14, gh, gw) float32 log-probabilities on the grid of grid_positions(H, W,
    p.stride), log(LOG_EPS) outside each image; adds the seconds of the features and of the
    traversal to timings."""
    sizes = [image.shape[:2] for image in group]
    t0 = time.perf_counter()
    probs = cascade_probs(layers, channels, p, sizes, mixtures, cells)[-1]
    timings["traversal"] += time.perf_counter() - t0
    if p.flip_test:
        mirrors = [mirror_on_grid(image, p.stride) for image in group]
        mirror_channels, mirror_sizes = group_channels(mirrors, timings, channels.device)
        if cells is not None:
            height, width = mirror_channels.shape[2], mirror_channels.shape[3]
            _, rows, cols = grid_positions(height, width, p.stride)
            cells = flip_columns(cells[:, None], sizes, p.stride, (len(group), 1, rows, cols))[:, 0]
        t0 = time.perf_counter()
        mirrored = cascade_probs(layers, mirror_channels, p, mirror_sizes, mixtures, cells)[-1]
        timings["traversal"] += time.perf_counter() - t0
        probs = (probs + unmirror(mirrored, sizes, p.stride, probs.shape)) / 2
    unaries = unaries_from_probs(probs, p.unary_blur)  # zero outside each image
    height, width = channels.shape[2], channels.shape[3]
    valid = valid_cells(sizes, height, width, p.stride, channels.device)  # (b, 1, gh, gw)
    return torch.where(valid, unaries, torch.full_like(unaries, np.log(LOG_EPS)))


def mirror_on_grid(image: np.ndarray, stride: int) -> np.ndarray:
    """(H, W, 3) -> the image mirrored left-right, less its first (W - 1) % stride columns, so
    that the grid of grid_positions on it is the image's own grid mirrored: column j of that
    grid lands on column (W - 1) // stride - j of the image's."""
    return np.ascontiguousarray(image[:, ::-1][:, (image.shape[1] - 1) % stride :])


def unmirror(
    probs: torch.Tensor, sizes: list[tuple[int, int]], stride: int, shape: torch.Size
) -> torch.Tensor:
    """Class probabilities (b, 15, gh', gw') of the images' mirror_on_grid -> on the images' own
    grids (b, 15, gh, gw) = shape: columns reversed, left and right swapped (background kept),
    zero outside each image; sizes: the b images' (h, w)."""
    return flip_columns(probs[:, [*FLIP, NUM_JOINTS]], sizes, stride, shape)


def flip_columns(
    maps: torch.Tensor, sizes: list[tuple[int, int]], stride: int, shape: tuple[int, ...]
) -> torch.Tensor:
    """Maps (b, C, gh', gw') on the grids of b images (h, w) = sizes -> (b, C, gh, gw) = shape,
    each image's cells with their columns reversed: from an image's grid to its mirror_on_grid's
    and back. Zero outside each image."""
    out = maps.new_zeros(shape)
    for k, (h, w) in enumerate(sizes):
        gh, gw = -(-h // stride), -(-w // stride)
        out[k, :, :gh, :gw] = maps[k, :, :gh, :gw].flip(-1)
    return out


# Bytes of a traversal group's padded channel stack (pad_channels). On the CPU, larger buffers are
# mmapped afresh by malloc on every call and page-faulted in: several small groups beat one large
# one. Off it, the allocator keeps its blocks, and each group is another round of kernel launches.
GROUP_BYTES = 16 * 2**20
DEVICE_GROUP_BYTES = 2**30


def traversal_groups(
    sizes: list[tuple[int, int]], last_layer: Forest, max_bytes: int = GROUP_BYTES
) -> list[list[int]]:
    """Rows of a batch of images (h, w) in groups run through the cascade together: images of
    similar shape (sorted by aspect ratio, so little of a group is padding), each group's padded
    stack of `last_layer`'s channels within max_bytes (at least one image per group)."""
    pad = 2 * last_layer.radius
    per_px = 4 * (last_layer.n_channels + 1)  # float32 bytes per padded pixel
    groups: list[list[int]] = []
    hmax = wmax = 0
    for i in sorted(range(len(sizes)), key=lambda i: (sizes[i][0] / sizes[i][1], i)):
        h, w = max(hmax, sizes[i][0]), max(wmax, sizes[i][1])
        if groups and (len(groups[-1]) + 1) * per_px * (h + pad) * (w + pad) <= max_bytes:
            groups[-1].append(i)
            hmax, wmax = h, w
        else:
            groups.append([i])
            hmax, wmax = sizes[i]
    return groups


def batch_channels(
    images: list[np.ndarray], height: int, width: int, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """Channels per image, zero-padded into a (B, 12, height, width) batch on `device`: exactly
    what a single image sees in training (zero outside the image), whatever the batch."""
    out = torch.zeros(len(images), NUM_IMAGE_CHANNELS, height, width, device=device)
    for i, r in enumerate(images):
        pixels = torch.from_numpy(r).to(device)[None]
        out[i, :, : r.shape[0], : r.shape[1]] = image_channels(pixels)[0]
    return out
