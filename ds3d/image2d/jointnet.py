"""A second unary: a small fully convolutional network that scores each joint's position.

The paper's PSM takes its unaries from "any discriminative model" (SVMs in Yang and Ramanan,
random forests in Dantone et al., which it follows). The forest cascade saturated against
every growing knob tried, and it cannot tell left from right: it reads pixels within 40 px of
each one. This network sees the whole person (a receptive field of about 300 px at the working
scale, where a person spans 100 px) and is trained on person-centric labels, so its maps carry
which arm is the right one. The PSM sums both unaries (InferenceParams.jointnet_weight,
left_right.settle_left_right); the forests stay the paper's unary. What each is worth:
docs/RESULTS.md, 2D stage.

Architecture (JointNet): two stride-2 3 x 3 convolutions to a quarter of the resolution, then
an hourglass of residual blocks down to stride 16 and back, a 1 x 1 convolution to 14 maps.
Output cell (u, v) is centred on input pixel (STRIDE * u, STRIDE * v). Input: Lab / 100
(features.lab_channels) at the working scale, zero outside the image (and in a MARGIN around
it at inference, as training windows reach past their images).

Its maps are softmaxed over each image's cells: P(joint at the cell), a distribution over
positions per joint, as trained (a cross-entropy against a Gaussian around the annotated
joint, ds3d.training.jointnet).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from ds3d.image2d.buckets import bucket
from ds3d.image2d.result import LOG_EPS
from ds3d.skeleton import FLIP, NUM_JOINTS
from ds3d.util.groups import group_rows

M = TypeVar("M", bound=nn.Module)  # fold_batch_norms gives back the network it was given

STRIDE = 4  # input px per output cell
# bfloat16 autocast on CPUs whose oneDNN computes it (AVX-512 and newer): twice float32's speed
# on this project's machines; elsewhere it would be emulated, slower than float32.
CPU_BFLOAT16 = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
# A person looks alike to the network from 1 / ZOOM_REACH to ZOOM_REACH times its canonical
# extent: the zoom it was trained with (ds3d.training.jointnet.ZOOM).
ZOOM_REACH = 1.3
MARGIN = 16  # px of zeros around an image at inference (logits_on_grid); a multiple of STRIDE
# The network's input is padded to buckets of NET_BUCKET_STEPS sizes per octave of each side,
# coarser than the rest of the 2D stage's: each new input shape costs oneDNN about 10 ms of
# primitive creation (two dozen convolutions), several times the convolutions' own time, and
# the primitive cache holds every shape met only where they are few.
NET_BUCKET_STEPS = 4
# Input px of the images the network takes in one call (padded_logits_each): batches as large
# as a call gains from, within a bound on the activations (about 130 MB each at stride 2).
NET_BATCH_PIXELS = 2**22


@dataclass(frozen=True)
class JointNetShape:
    """Channels and residual blocks of the network at strides 4, 8 and 16 (input px per cell).
    Most of the capacity sits at strides 8 and 16, where a convolution costs a quarter and a
    sixteenth of one at stride 4, and gives the receptive field that sees the whole person."""

    widths: tuple[int, int, int] = (64, 128, 192)
    blocks: tuple[int, int, int] = (1, 2, 2)


def _conv_bn(cin: int, cout: int, kernel: int = 3, stride: int = 1, dilation: int = 1):
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride, dilation * (kernel // 2), dilation, bias=False),
        nn.BatchNorm2d(cout),
    )


class _Residual(nn.Module):
    def __init__(self, width: int, dilation: int = 1):
        super().__init__()
        self.body = nn.Sequential(
            _conv_bn(width, width, dilation=dilation), nn.ReLU(), _conv_bn(width, width)
        )

    def forward(self, x: Tensor) -> Tensor:
        return torch.relu(x + self.body(x))


class _Down(nn.Sequential):
    """A stride-2 convolution to `cout` channels, then residual blocks (dilations alternating 1
    and 2: a wider field at the same cost)."""

    def __init__(self, cin: int, cout: int, blocks: int):
        super().__init__(
            _conv_bn(cin, cout, stride=2),
            nn.ReLU(),
            *[_Residual(cout, 1 + k % 2) for k in range(blocks)],
        )


class _Up(nn.Module):
    """A coarse map upsampled onto a finer one's cells and added to it, then a residual block."""

    def __init__(self, coarse: int, fine: int):
        super().__init__()
        self.coarse = _conv_bn(coarse, fine, kernel=1)
        self.fine = _conv_bn(fine, fine, kernel=1)
        self.block = _Residual(fine)

    def forward(self, coarse: Tensor, fine: Tensor) -> Tensor:
        up = F.interpolate(self.coarse(coarse), size=fine.shape[-2:], mode="bilinear")
        return self.block(torch.relu(up + self.fine(fine)))


class JointNet(nn.Module):
    """(B, 3, H, W) Lab / 100 -> (B, 14, ceil(H / 4), ceil(W / 4)) joint logits: an hourglass,
    down to stride 16 and back up to stride 4 with skip connections (JointNetShape). With the
    default shape 2.7M parameters, about 0.55 G multiply-adds for a 128 x 128 input."""

    def __init__(self, shape: JointNetShape = JointNetShape()):
        super().__init__()
        w4, w8, w16 = shape.widths
        n4, n8, n16 = shape.blocks
        self.stem = nn.Sequential(
            _conv_bn(3, 32, stride=2),
            nn.ReLU(),
            _conv_bn(32, w4, stride=2),
            nn.ReLU(),
            *[_Residual(w4) for _ in range(n4)],
        )
        self.down8 = _Down(w4, w8, n8)
        self.down16 = _Down(w8, w16, n16)
        self.up8 = _Up(w16, w8)
        self.up4 = _Up(w8, w4)
        self.head = nn.Conv2d(w4, NUM_JOINTS, 1)

    def forward(self, lab: Tensor) -> Tensor:
        x4 = self.stem(lab)
        x8 = self.down8(x4)
        x16 = self.down16(x8)
        return self.head(self.up4(self.up8(x16, x8), x4))


def fold_batch_norms(net: M) -> M:
    """For inference: every convolution followed by a batch norm (in eval mode, an affine map
    per channel) becomes one convolution, in place; one pass over the maps less for each.
    Returns net, in eval mode."""
    net.eval()
    for module in net.modules():
        for name, child in module.named_children():
            if (
                isinstance(child, nn.Sequential)
                and len(child) == 2
                and isinstance(child[0], nn.Conv2d)
                and isinstance(child[1], nn.BatchNorm2d)
            ):
                setattr(module, name, fuse_conv_bn_eval(child[0], child[1]))
    return net


def padded_logits(net: nn.Module, lab: Tensor) -> Tensor:
    """The network's logits of images inside a MARGIN px border of zeros, as training windows
    extend past their images (its effect: docs/tuning.md): lab (B, 3, H, W) Lab / 100 ->
    (B, 14, ceil((H + 2 MARGIN) / STRIDE), ceil((W + 2 MARGIN) / STRIDE)) float32. The network
    runs on more zeros below and right of that border, up to the bucket of each side at
    NET_BUCKET_STEPS per octave (ds3d.image2d.buckets). Computed in the network's dtype and on
    its device: bfloat16 as load_jointnet leaves it on a CPU that computes it (CPU_BFLOAT16), or
    a float32 network under bfloat16 autocast there, as trained; returned on its device."""
    height, width = lab.shape[-2:]
    padded = _run(net, _net_input(lab, MARGIN, NET_BUCKET_STEPS))
    return _crop_logits(padded, height, width, MARGIN).contiguous()


def padded_logits_each(
    net: nn.Module, labs: Sequence[Tensor], margin: int = MARGIN, steps: int = NET_BUCKET_STEPS
) -> list[Tensor]:
    """padded_logits of each of N images of any sizes, labs (1, 3, H_i, W_i) Lab / 100 -> N
    (1, 14, ceil((H_i + 2 margin) / STRIDE), ceil((W_i + 2 margin) / STRIDE)), inside `margin`
    px of zeros and padded to buckets of `steps` per octave (a caller whose images carry their
    own border of zeros asks for less; margin a multiple of STRIDE). The images whose padded
    input is of one shape (one bucket) go through the network in one call, at most
    NET_BATCH_PIXELS px of input a call: batched, the network costs a fraction of its cost one
    image at a time (16 inputs of 144 x 112 px on one thread: 1.9 against 4.9 ms an image, of
    96 x 64: 0.8 against 3.6 ms). An image's maps are those it gets alone,
    up to the float rounding of a larger batch: it sees its own zeros, not its neighbours'."""
    inputs = network_inputs(labs, margin, steps)
    found: dict[int, Tensor] = {}
    for (height, width), rows in group_rows(x.shape[-2:] for x in inputs).items():
        per_call = max(1, NET_BATCH_PIXELS // (height * width))
        for start in range(0, len(rows), per_call):
            chunk = rows[start : start + per_call]
            logits = _run(net, torch.cat([inputs[i] for i in chunk]))
            for i, maps in zip(chunk, logits, strict=True):
                h, w = labs[i].shape[-2:]
                found[i] = _crop_logits(maps[None], h, w, margin).contiguous()
    return [found[i] for i in range(len(labs))]


def network_inputs(labs: Sequence[Tensor], margin: int, steps: int) -> list[Tensor]:
    """labs (B, 3, H, W) -> the network's inputs (padded_logits_each): each inside a `margin` px
    border of zeros, then zeros below and right up to the bucket of each side at `steps` per
    octave."""
    return [_net_input(lab, margin, steps) for lab in labs]


def _net_input(lab: Tensor, margin: int, steps: int) -> Tensor:
    """network_inputs of one lab."""
    height, width = lab.shape[-2:]
    right = bucket(width + 2 * margin, steps) - width - margin
    bottom = bucket(height + 2 * margin, steps) - height - margin
    return F.pad(lab, (margin, right, margin, bottom))


def _run(net: nn.Module, padded: Tensor) -> Tensor:
    """The network on its padded input (B, 3, H', W') in its dtype and on its device (as
    padded_logits; an int8 network, ds3d.image2d.quantized, on float32 input on the CPU) ->
    (B, 14, H' / STRIDE, W' / STRIDE) float32 logits on its device."""
    if getattr(net, "int8", False):  # ONNX Runtime's, on the CPU (ds3d.image2d.quantized)
        return net(padded)
    weight = next(net.parameters(), padded)
    autocast = weight.dtype == torch.float32 and weight.is_cpu and CPU_BFLOAT16
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        # channels-last, as trained: the memory format oneDNN's convolutions run fastest in
        padded = padded.to(weight.device, weight.dtype, memory_format=torch.channels_last)
        return net(padded).float()


def _crop_logits(logits: Tensor, height: int, width: int, margin: int) -> Tensor:
    """The cells of a (height, width) image's logits inside `margin` px of zeros out of the
    network's output on its bucket-padded input."""
    return logits[..., : -(-(height + 2 * margin) // STRIDE), : -(-(width + 2 * margin) // STRIDE)]


@dataclass(frozen=True)
class ScaledLogits:
    """The network's logits (1, 14, h, w) of an image resized by `scale` (resized px per image
    px, (x, y)), whose input reached `border` px of zeros past the resized image on every side
    (MARGIN: padded_logits'; the search's levels carry their own): the search's levels, off
    which the 2D stage reads its crops' maps (read_logits)."""

    logits: Tensor
    scale: tuple[float, float]
    border: int = MARGIN


def read_logits(
    views: Sequence[ScaledLogits],
    scale: tuple[float, float],
    offset: tuple[float, float],
    height: int,
    width: int,
) -> Tensor | None:
    """The padded_logits of a (height, width) image whose px (x, y) lies at image px
    (x + 0.5) / scale - 0.5 + offset (a crop at offset, resized by scale), read off the view
    of the image nearest its scale (resampled_logits); None where none is within the zoom the
    network was trained with (ZOOM_REACH)."""
    nearest = min(views, key=lambda v: abs(math.log(v.scale[0] / scale[0])), default=None)
    if nearest is None or abs(math.log(nearest.scale[0] / scale[0])) > math.log(ZOOM_REACH):
        return None
    ratio = (nearest.scale[0] / scale[0], nearest.scale[1] / scale[1])
    shift = tuple(
        (0.5 / f + o) * v - 0.5 + nearest.border
        for f, o, v in zip(scale, offset, nearest.scale, strict=True)
    )
    return resampled_logits(nearest.logits, ratio, (shift[0], shift[1]), height, width)


def resampled_logits(
    source: Tensor, scale: tuple[float, float], offset: tuple[float, float], height: int, width: int
) -> Tensor:
    """What padded_logits would be for a (height, width) image, read bilinearly off `source`,
    the logits (1, 14, h', w') of another view of the same scene, in whose input (px from its
    first cell's centre) this image's px (x, y) lies at scale * (x, y) + offset (past its last
    cell, the last) -> (1, 14, ceil((height + 2 MARGIN) / STRIDE), ceil((width + 2 MARGIN) /
    STRIDE)). The network sees a person alike within the zoom it was trained with (about 0.7
    to 1.3), so one view's maps serve another's scale in that range."""
    oh, ow = source.shape[-2:]
    axes = []
    for size, cells, k in ((width, ow, 0), (height, oh, 1)):
        cells_out = -(-(size + 2 * MARGIN) // STRIDE)
        px = torch.arange(cells_out, dtype=torch.float32, device=source.device) * STRIDE - MARGIN
        cell = (scale[k] * px + offset[k]) / STRIDE  # source cells
        axes.append(cell / max(cells - 1, 1) * 2 - 1)
    xs, ys = axes
    grid = torch.stack([xs[None, :].expand(len(ys), -1), ys[:, None].expand(-1, len(xs))], -1)[None]
    return F.grid_sample(source, grid, mode="bilinear", padding_mode="border", align_corners=True)


def logits_to_grid(
    logits: Tensor,
    height: int,
    width: int,
    stride: int,
    mirrored: bool = False,
    margin: int = MARGIN,
) -> Tensor:
    """The network's logits of (height, width) images inside `margin` px of zeros (padded_logits
    and MARGIN, by default) -> their values on the grid of cascade.grid_positions(height, width,
    stride): (B, 14, ceil(height / stride), ceil(width / stride)). Grid cell (i, j) is pixel
    (stride * i, stride * j), so output cell ((stride * i + margin) / STRIDE, (stride * j +
    margin) / STRIDE): read bilinearly (past the last output cell, the last). mirrored: the
    logits are of the images mirrored left to right; they are read at the mirrored pixels, left
    and right swapped, so that they describe the images themselves."""
    gh, gw = -(-height // stride), -(-width // stride)
    ys = (torch.arange(gh, dtype=torch.float32, device=logits.device) * stride + margin) / STRIDE
    px = torch.arange(gw, dtype=torch.float32, device=logits.device) * stride
    xs = ((width - 1 - px if mirrored else px) + margin) / STRIDE
    oh, ow = logits.shape[-2:]
    grid = torch.stack(
        [
            (xs / max(ow - 1, 1) * 2 - 1)[None, :].expand(gh, gw),
            (ys / max(oh - 1, 1) * 2 - 1)[:, None].expand(gh, gw),
        ],
        -1,
    )
    grid = grid[None].expand(len(logits), gh, gw, 2)
    out = F.grid_sample(logits, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, list(FLIP)] if mirrored else out


def logits_on_grid(
    net: nn.Module,
    lab: Tensor,
    stride: int,
    flip_test: bool = False,
    padded: Tensor | None = None,
) -> Tensor:
    """The network's logits of lab (B, 3, H, W) Lab / 100 on the grid of
    cascade.grid_positions(H, W, stride): (B, 14, ceil(H / stride), ceil(W / stride)).
    flip_test: the mean of the logits of the images and of their mirror images. padded: the
    images' padded_logits where already computed."""
    padded = padded_logits(net, lab) if padded is None else padded
    mirrored = padded_logits(net, lab.flip(-1)) if flip_test else None
    return _grid_logits(padded, mirrored, lab.shape[-2], lab.shape[-1], stride)


def _grid_logits(
    padded: Tensor, mirrored: Tensor | None, height: int, width: int, stride: int
) -> Tensor:
    """logits_on_grid of (height, width) images from their padded_logits, and with flip_test
    their mirror images' (else None)."""
    logits = logits_to_grid(padded, height, width, stride)
    if mirrored is None:
        return logits
    return (logits + logits_to_grid(mirrored, height, width, stride, mirrored=True)) / 2


def spatial_softmax(logits: Tensor) -> Tensor:
    """Per joint, a softmax over the cells: (B, 14, H, W) logits -> (B, 14, H, W) P(joint at
    the cell), each map summing to 1."""
    b, j, h, w = logits.shape
    return torch.softmax(logits.reshape(b, j, h * w), -1).reshape(b, j, h, w)


def unaries_from_logits(logits: Tensor) -> Tensor:
    """Logits (B, 14, h, w) on a grid -> log(P(joint at the cell) + LOG_EPS), floored as the
    forests' unaries are."""
    return (spatial_softmax(logits) + LOG_EPS).log()


def jointnet_unaries(
    net: nn.Module,
    channels: Tensor,
    sizes: list[tuple[int, int]],
    stride: int,
    flip_test: bool = False,
    padded: Sequence[Tensor | None] | None = None,
) -> Tensor:
    """The joint network's unaries on the grid: channels (b, 12, H, W) zero-padded, sizes b
    (h, w) -> (b, 14, gh, gw) unaries_from_logits; log(LOG_EPS) outside each image. Each image
    runs on its own pixels and its own padding (padded_logits_each), not the group's: past the
    first convolution's bias, zeros are no longer zeros, and the network sees the whole person
    around each cell. flip_test, padded (b of them): as logits_on_grid."""
    h, w = channels.shape[-2:]
    labs = [channels[i : i + 1, :3, :hi, :wi] for i, (hi, wi) in enumerate(sizes)]
    known = list(padded) if padded is not None else [None] * len(labs)
    missing = [i for i, k in enumerate(known) if k is None]
    computed = dict(zip(missing, padded_logits_each(net, [labs[i] for i in missing]), strict=True))
    logits = [computed[i] if k is None else k for i, k in enumerate(known)]
    mirrored: list[Tensor | None] = [None] * len(labs)
    if flip_test:
        mirrored = [*padded_logits_each(net, [lab.flip(-1) for lab in labs])]
    shape = (len(sizes), NUM_JOINTS, -(-h // stride), -(-w // stride))
    out = channels.new_full(shape, np.log(LOG_EPS))
    for i, (hi, wi) in enumerate(sizes):
        grid = _grid_logits(logits[i], mirrored[i], hi, wi, stride)
        out[i, :, : grid.shape[2], : grid.shape[3]] = unaries_from_logits(grid)[0]
    return out
