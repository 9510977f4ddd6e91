"""Max-convolution of a score map with a mixture of axis-aligned Gaussian log-kernels: the
message of one limb in max-product inference of a pictorial structure model.

For a child score map S (unary plus the messages of the child's own children) and a mixture
with means mu_c, per-axis variances v_c and log-weights g_c, the message to the parent is

    M(x_j) = max_c [ g_c + max_{x_i} S(x_i) - 0.5 sum_k (x_i,k - x_j,k - mu_c,k)^2 / v_c,k ]

over the grid. Everything here is in grid cells; the caller converts pixels (ds3d.image2d.psm).

The quadratic is axis-aligned, so the inner max is separable: a pass along x, then a pass along y,
each exact over the full range of the grid (no truncation, so no window to tune). Each pass is a
broadcast add into a contiguous buffer whose outermost axis is the source axis, then an `amax`
over that axis, in chunks of about `chunk_elements` candidates so that the buffer stays in cache.
Measured on one CPU thread of the 2-core dev machine (load ~3.5, medians): add + amax of 2
components on a 78 x 78 grid took 0.28 ms in this layout against 0.62 ms with the source axis
innermost but one (torch's default layout for the broadcast), and 5 components on 57 x 57 took
0.33 vs 1.41 ms: about 3e9 candidates/s; a loop over the offsets of a bounded window (with
argmax bookkeeping) ran at 0.2e9/s. No argmax is kept here: back-tracking needs it at one parent
cell per limb only, and `best_child` recomputes it there exactly.
"""

from __future__ import annotations

import torch
from torch import Tensor

CHUNK_ELEMENTS = 1 << 20
# Off the CPU there is no cache to stay in, and each chunk is another few kernel launches: far
# larger chunks (256 MB of float32 buffer), so that a batch's maps go in a few calls.
DEVICE_CHUNK_ELEMENTS = 1 << 26


def _axis_kernel(size: int, mean: Tensor, var: Tensor) -> Tensor:
    """Log-kernel along one axis. mean, var: (n, C) cells -> (n, C, size_src, size_dst) with
    k[..., a, b] = -0.5 (a - b - mean)^2 / var, i.e. source index a, destination index b."""
    grid = torch.arange(size, dtype=mean.dtype, device=mean.device)
    delta = grid[:, None] - grid[None, :]  # (src, dst): a - b
    diff = delta - mean[..., None, None]
    return -0.5 * diff * diff / var[..., None, None]


def max_convolve(
    scores: Tensor,
    mean: Tensor,
    var: Tensor,
    log_weight: Tensor,
    chunk_elements: int | None = None,
) -> Tensor:
    """Message of a child score map to every parent cell, maximised over mixture components.

    scores: (N, H, W) child scores (log domain; -inf allowed, +inf and NaN not).
    mean: (N or 1, C, 2) component means of the offset child - parent, cells, (x, y).
    var: (N or 1, C, 2) per-axis variances, cells^2, > 0.
    log_weight: (N or 1, C) log mixture weights (-inf switches a component off).
    Returns (N, H, W) in the dtype of `scores`: M(x_j) as in the module docstring.
    A leading dimension 1 in the mixture means one mixture for all N maps.
    chunk_elements: candidates per buffer (None: CHUNK_ELEMENTS on the CPU, DEVICE_CHUNK_ELEMENTS
    elsewhere).
    """
    n, height, width = scores.shape
    n_comp = mean.shape[1]
    shared = mean.shape[0] == 1
    if mean.shape[0] not in (1, n) or var.shape != mean.shape or log_weight.shape != mean.shape[:2]:
        raise ValueError(
            f"mixture shapes {tuple(mean.shape)}, {tuple(var.shape)}, {tuple(log_weight.shape)}"
            f" do not fit {n} score maps"
        )
    mean, var, log_weight = (t.to(scores.dtype) for t in (mean, var, log_weight))
    if chunk_elements is None:
        chunk_elements = CHUNK_ELEMENTS if scores.is_cpu else DEVICE_CHUNK_ELEMENTS
    per_map = height * width * max(height, width)  # candidates of one component in one pass
    comp_chunk = max(1, min(n_comp, chunk_elements // per_map))
    map_chunk = max(1, chunk_elements // (per_map * comp_chunk)) if comp_chunk == n_comp else 1
    if shared:
        kx_all = _axis_kernel(width, mean[..., 0], var[..., 0])  # (1, C, W, W)
        ky_all = _axis_kernel(height, mean[..., 1], var[..., 1])  # (1, C, H, H)
    # One buffer for the broadcast sums of both passes, so that they are contiguous with the
    # reduced axis outermost: amax then takes elementwise maxima of whole (H, W) planes. Left to
    # itself, torch lays the x-pass sum out with the source axis innermost but one, and amax
    # over it ran 2-4x slower whenever W was not a multiple of 16.
    buffer = scores.new_empty(map_chunk * comp_chunk * per_map)
    src = scores.transpose(1, 2)  # (N, W_src, H)
    out = torch.empty_like(scores)
    for m0 in range(0, n, map_chunk):
        m1 = min(n, m0 + map_chunk)
        if shared:
            kx, ky, lw = kx_all, ky_all, log_weight
        else:
            kx = _axis_kernel(width, mean[m0:m1, :, 0], var[m0:m1, :, 0])
            ky = _axis_kernel(height, mean[m0:m1, :, 1], var[m0:m1, :, 1])
            lw = log_weight[m0:m1]
        best = None
        for c0 in range(0, n_comp, comp_chunk):
            c1 = min(n_comp, c0 + comp_chunk)
            m, c = m1 - m0, c1 - c0
            # x pass: (m, c, W_src, H, W_dst) -> max over W_src
            sums = buffer[: m * c * width * height * width].view(m, c, width, height, width)
            torch.add(src[m0:m1, None, :, :, None], kx[:, c0:c1, :, None, :], out=sums)
            along_x = sums.amax(dim=2)
            # y pass: (m, c, H_src, H_dst, W) -> max over H_src
            sums = buffer[: m * c * height * height * width].view(m, c, height, height, width)
            torch.add(along_x[:, :, :, None, :], ky[:, c0:c1, :, :, None], out=sums)
            along_y = sums.amax(dim=2)
            msg = (along_y + lw[:, c0:c1, None, None]).amax(dim=1)
            best = msg if best is None else torch.maximum(best, msg)
        assert best is not None, "no mixture component"
        out[m0:m1] = best
    return out


def best_child(
    scores: Tensor, parent: Tensor, mean: Tensor, var: Tensor, log_weight: Tensor
) -> tuple[Tensor, Tensor]:
    """The maximiser of the message at one parent cell per map (the back-tracking step).

    scores: (N, H, W); parent: (N, 2) long cells (x, y); mean, var, log_weight as in
    `max_convolve` (leading dimension N or 1).
    Returns (cells (N, 2) long (x, y) of the best child cell, value (N,) = the message there).
    """
    n, height, width = scores.shape
    mean, var, log_weight = (t.to(scores.dtype) for t in (mean, var, log_weight))
    xs = torch.arange(width, dtype=scores.dtype, device=scores.device)
    ys = torch.arange(height, dtype=scores.dtype, device=scores.device)
    px = parent[:, 0, None].to(scores.dtype)  # (N, 1)
    py = parent[:, 1, None].to(scores.dtype)
    dx = xs[None, None, :] - px[:, :, None] - mean[..., 0, None]  # (N, C, W)
    dy = ys[None, None, :] - py[:, :, None] - mean[..., 1, None]  # (N, C, H)
    cost = (-0.5 * dy * dy / var[..., 1, None])[..., :, None] + (
        -0.5 * dx * dx / var[..., 0, None]
    )[..., None, :]  # (N, C, H, W)
    total = scores[:, None] + cost + log_weight[..., None, None]
    value, flat = total.reshape(n, -1).max(dim=1)
    cell = flat % (height * width)
    return torch.stack((cell % width, cell // width), dim=1), value
