"""Per-pixel feature channels and the randomised pixel-comparison features a forest splits on.

Channels (12, all float32, computed batched in torch):
    0-2   CIE Lab colour (L / 100, a / 100, b / 100)
    3     gradient magnitude of L
    4-11  8 unsigned orientation bins of the gradient (soft-binned magnitude, 5x5 box-pooled),
          a dense HOG-like cell histogram

A pixel-comparison feature f reads one channel c at two offsets from the pixel p:
    f(p) = ch_c(p + o1) - w2 * ch_c(p + o2),   w2 in {0, 1}
so w2 = 0 gives the raw channel value at an offset. Offsets are integer pixels (dy, dx) at the
working scale, |dy|, |dx| <= radius. Channel maps are zero-padded by `radius` so every read stays
in bounds (outside the image reads 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

NUM_IMAGE_CHANNELS = 12
NUM_ORIENTATIONS = 8


def _srgb_to_linear_table() -> torch.Tensor:
    v = torch.arange(256, dtype=torch.float64) / 255.0
    return torch.where(v > 0.04045, ((v + 0.055) / 1.055) ** 2.4, v / 12.92).float()


_SRGB_TO_LINEAR = _srgb_to_linear_table()


def rgb_to_lab(rgb: torch.Tensor) -> torch.Tensor:
    """sRGB (D65) to CIE Lab. rgb: (B, 3, H, W) uint8 -> (B, 3, H, W) float32, L in [0, 100]."""
    # a table lookup: pow(2.4) per pixel is costly on CPU
    linear = _SRGB_TO_LINEAR.to(rgb.device)[rgb.long()]
    m = torch.tensor(
        [
            [0.412453 / 0.950456, 0.357580 / 0.950456, 0.180423 / 0.950456],
            [0.212671, 0.715160, 0.072169],
            [0.019334 / 1.088754, 0.119193 / 1.088754, 0.950227 / 1.088754],
        ],
        dtype=linear.dtype,
        device=linear.device,
    )
    xyz = torch.einsum("ij,bjhw->bihw", m, linear)
    delta = 6.0 / 29.0
    f = torch.where(
        xyz > delta**3, xyz.clamp_min(1e-12) ** (1.0 / 3.0), xyz / (3 * delta**2) + 4.0 / 29.0
    )
    lum = 116.0 * f[:, 1] - 16.0
    a = 500.0 * (f[:, 0] - f[:, 1])
    b = 200.0 * (f[:, 1] - f[:, 2])
    return torch.stack([lum, a, b], dim=1)


def box_mean(x: torch.Tensor, r: int) -> torch.Tensor:
    """Mean over a (2r+1)^2 box, zeros outside. x: (B, C, H, W) -> same shape.

    Integral-image differences: O(1) per pixel (avg_pool2d with stride 1 is ~20x slower on CPU).
    """
    k = 2 * r + 1
    p = F.pad(x, (r + 1, r, r + 1, r)).cumsum(2).cumsum(3)
    s = p[:, :, k:, k:] - p[:, :, :-k, k:] - p[:, :, k:, :-k] + p[:, :, :-k, :-k]
    return s / (k * k)


def lab_channels(images: torch.Tensor) -> torch.Tensor:
    """Channels 0-2 of image_channels alone. images: (B, H, W, 3) uint8 RGB -> (B, 3, H, W)
    float32, Lab / 100."""
    return rgb_to_lab(images.permute(0, 3, 1, 2)) / 100.0


def image_channels(images: torch.Tensor) -> torch.Tensor:
    """Feature channels of a batch of images.

    images: (B, H, W, 3) uint8 RGB -> (B, 12, H, W) float32.
    """
    lab = lab_channels(images)
    # Sobel by slicing (mkldnn conv2d costs ~1 ms per small image on CPU).
    p = F.pad(lab[:, :1], (1, 1, 1, 1), mode="replicate")[:, 0]
    sx = p[:, :, 2:] - p[:, :, :-2]  # (B, H + 2, W)
    sy = p[:, 2:, :] - p[:, :-2, :]  # (B, H, W + 2)
    gx = (sx[:, :-2] + 2 * sx[:, 1:-1] + sx[:, 2:]) / 8.0
    gy = (sy[:, :, :-2] + 2 * sy[:, :, 1:-1] + sy[:, :, 2:]) / 8.0
    mag = torch.sqrt(gx * gx + gy * gy)
    # Unsigned orientation in [0, pi), soft-assigned to the two nearest of 8 bins.
    theta = torch.remainder(torch.atan2(gy, gx), math.pi) * (NUM_ORIENTATIONS / math.pi)
    lo = torch.floor(theta)
    frac = theta - lo
    lo = lo.long() % NUM_ORIENTATIONS
    hi = (lo + 1) % NUM_ORIENTATIONS
    hist = mag.new_zeros(mag.shape[0], NUM_ORIENTATIONS, *mag.shape[1:])
    hist.scatter_add_(1, lo.unsqueeze(1), (mag * (1 - frac)).unsqueeze(1))
    hist.scatter_add_(1, hi.unsqueeze(1), (mag * frac).unsqueeze(1))
    hist = box_mean(hist, 2)
    return torch.cat([lab, mag.unsqueeze(1), hist], dim=1).contiguous()


@dataclass(frozen=True)
class ComparisonPool:
    """A pool of F pixel-comparison features.

    channel: (F,) int64; offset1, offset2: (F, 2) int64 (dy, dx) pixels; use2: (F,) float32 in
    {0, 1}.
    """

    channel: np.ndarray
    offset1: np.ndarray
    offset2: np.ndarray
    use2: np.ndarray

    def __len__(self) -> int:
        return len(self.channel)


def sample_pool(
    rng: np.random.Generator,
    n: int,
    radius: int,
    n_image_channels: int = NUM_IMAGE_CHANNELS,
    n_context_channels: int = 0,
    context_fraction: float = 0.5,
) -> ComparisonPool:
    """Draw n random comparisons with offsets in [-radius, radius]^2.

    Channels index [image channels..., context channels...]; when context channels exist, a
    `context_fraction` of the features reads one of them.
    """
    if n_context_channels:
        is_ctx = rng.random(n) < context_fraction
        channel = np.where(
            is_ctx,
            n_image_channels + rng.integers(0, n_context_channels, n),
            rng.integers(0, n_image_channels, n),
        )
    else:
        channel = rng.integers(0, n_image_channels, n)
    offset1 = rng.integers(-radius, radius + 1, (n, 2))
    offset2 = rng.integers(-radius, radius + 1, (n, 2))
    use2 = (rng.random(n) < 0.5).astype(np.float32)
    return ComparisonPool(channel.astype(np.int64), offset1, offset2, use2)


def pad_channels(channels: torch.Tensor, radius: int) -> torch.Tensor:
    """Zero-pad (B, C, H, W) by `radius` on every side and append one all-zero plane
    -> (B, C + 1, H + 2r, W + 2r). A comparison with use2 = 0 reads its second value from the zero
    plane, so every comparison is the same two gathers and one subtraction."""
    b, c, h, w = channels.shape
    out = channels.new_zeros(b, c + 1, h + 2 * radius, w + 2 * radius)
    out[:, :c, radius : radius + h, radius : radius + w] = channels
    return out


def second_reads(
    channel: torch.Tensor, dy2: torch.Tensor, dx2: torch.Tensor, use2: torch.Tensor, zero_plane: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Channel and offset of each comparison's second read: its own where use2 = 1, else the
    all-zero plane (channel `zero_plane`, pad_channels' last) at the pixel itself, so that every
    comparison is the same two reads and one subtraction. All (F,) -> three (F,) tensors."""
    use = use2 > 0
    return torch.where(use, channel, zero_plane), torch.where(use, dy2, 0), torch.where(use, dx2, 0)


def read_offsets(
    channel: torch.Tensor, dy: torch.Tensor, dx: torch.Tensor, padded_shape: tuple[int, ...]
) -> torch.Tensor:
    """Flat offset of a read (channel, dy, dx), relative to the pixel, in one image's padded
    stack of shape padded_shape = (C + 1, Hp, Wp). (F,) integer tensors -> (F,), same dtype."""
    _, hp, wp = padded_shape
    return channel * (hp * wp) + dy * wp + dx


def evaluate_pool(
    padded: torch.Tensor, radius: int, positions: torch.Tensor, pool: ComparisonPool
) -> torch.Tensor:
    """Evaluate every feature of the pool at given pixels of ONE image.

    padded: (C + 1, H + 2r, W + 2r) from pad_channels; positions: (P, 2) int64 (y, x) in the
    UNPADDED image -> (P, F) float32. Same reads and arithmetic as the tensorised traversal, so
    a forest trained on these values takes the same branches at inference.
    """
    _, _, wp = padded.shape
    flat = padded.reshape(-1)
    pix = (positions[:, 0] + radius) * wp + (positions[:, 1] + radius)  # (P,)
    channel = torch.as_tensor(pool.channel)
    o1 = torch.as_tensor(pool.offset1)
    o2 = torch.as_tensor(pool.offset2)
    second = second_reads(channel, o2[:, 0], o2[:, 1], torch.as_tensor(pool.use2), len(padded) - 1)
    base1 = read_offsets(channel, o1[:, 0], o1[:, 1], tuple(padded.shape))
    base2 = read_offsets(*second, tuple(padded.shape))
    return flat[pix[:, None] + base1[None, :]] - flat[pix[:, None] + base2[None, :]]
