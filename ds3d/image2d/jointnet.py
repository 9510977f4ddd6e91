"""A second unary: a small fully convolutional network that scores each joint's position.

The paper's PSM takes its unaries from "any discriminative model" (SVMs in Yang and Ramanan,
random forests in Dantone et al., which it follows). The forest cascade saturated against
every growing knob tried, and it cannot tell left from right: it reads pixels within 40 px of
each one. This network sees the whole person (a receptive field of about 300 px at the working
scale, where a person spans 100 px) and is trained on person-centric labels, so its maps carry
which arm is the right one. The PSM sums both unaries (InferenceParams.jointnet_weight,
left_right.left_right_hypotheses); the forests stay the paper's unary. What each is worth:
docs/RESULTS.md, 2D stage.

Architecture (JointNet): two stride-2 3 x 3 convolutions to a quarter of the resolution, then
residual blocks of dilated 3 x 3 convolutions (dilations 1, 2, 4, 8, 1), a 1 x 1 convolution to
14 maps. Output cell (u, v) is centred on input pixel (STRIDE * u, STRIDE * v). Input: Lab / 100
(features.lab_channels) at the working scale, zero outside the image (and in a MARGIN around
it at inference, as training windows reach past their images).

Its maps are softmaxed over each image's cells: P(joint at the cell), a distribution over
positions per joint, as trained (a cross-entropy against a Gaussian around the annotated
joint, ds3d.training.jointnet).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ds3d.image2d.result import LOG_EPS
from ds3d.skeleton import NUM_JOINTS

STRIDE = 4  # input px per output cell
# bfloat16 autocast on CPUs whose oneDNN computes it (AVX-512 and newer): twice float32's speed
# on this project's machines; elsewhere it would be emulated, slower than float32.
CPU_BFLOAT16 = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
MARGIN = 16  # px of zeros around an image at inference (logits_on_grid); a multiple of STRIDE
DILATIONS = (1, 2, 4, 8, 1)
WIDTH = 64


def _conv_bn(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> list[nn.Module]:
    return [
        nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
    ]


class _Residual(nn.Module):
    def __init__(self, width: int, dilation: int):
        super().__init__()
        self.body = nn.Sequential(
            *_conv_bn(width, width, dilation=dilation), nn.ReLU(), *_conv_bn(width, width)
        )

    def forward(self, x: Tensor) -> Tensor:
        return torch.relu(x + self.body(x))


class JointNet(nn.Module):
    """(B, 3, H, W) Lab / 100 -> (B, 14, ceil(H / 4), ceil(W / 4)) joint logits. 400k
    parameters, about 0.3 G multiply-adds for a 128 x 128 input."""

    def __init__(self, width: int = WIDTH, dilations: tuple[int, ...] = DILATIONS):
        super().__init__()
        self.layers = nn.Sequential(
            *_conv_bn(3, 32, stride=2), nn.ReLU(),
            *_conv_bn(32, 32), nn.ReLU(),
            *_conv_bn(32, width, stride=2), nn.ReLU(),
            *[_Residual(width, d) for d in dilations],
            nn.Conv2d(width, NUM_JOINTS, 1),
        )  # fmt: skip

    def forward(self, lab: Tensor) -> Tensor:
        return self.layers(lab)


def logits_on_grid(net: JointNet, lab: Tensor, stride: int) -> Tensor:
    """The network's logits resampled onto the grid of estimator.grid_positions(H, W, stride):
    lab (B, 3, H, W) Lab / 100 -> (B, 14, ceil(H / stride), ceil(W / stride)) float32.

    The image is run inside a MARGIN px border of zeros, as training windows extend past their
    images (its effect: docs/RESULTS.md). Grid cell
    (i, j) is pixel (stride * i, stride * j), so output cell ((stride * i + MARGIN) / STRIDE,
    (stride * j + MARGIN) / STRIDE): read bilinearly (past the last output cell, the last).
    bfloat16 on a CPU that computes it (CPU_BFLOAT16), as trained."""
    height, width = lab.shape[-2:]
    padded = F.pad(lab, (MARGIN, MARGIN, MARGIN, MARGIN))
    bf16 = lab.is_cpu and CPU_BFLOAT16
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        logits = net(padded).float()
    gh, gw = -(-height // stride), -(-width // stride)
    ys = (torch.arange(gh, dtype=torch.float32) * stride + MARGIN) / STRIDE
    xs = (torch.arange(gw, dtype=torch.float32) * stride + MARGIN) / STRIDE
    oh, ow = logits.shape[-2:]
    grid = torch.stack(
        [
            (xs / max(ow - 1, 1) * 2 - 1)[None, :].expand(gh, gw),
            (ys / max(oh - 1, 1) * 2 - 1)[:, None].expand(gh, gw),
        ],
        -1,
    )
    grid = grid[None].expand(len(logits), gh, gw, 2)
    return F.grid_sample(logits, grid, mode="bilinear", padding_mode="border", align_corners=True)


def spatial_softmax(logits: Tensor) -> Tensor:
    """Per joint, a softmax over the cells: (B, 14, H, W) logits -> (B, 14, H, W) P(joint at
    the cell), each map summing to 1."""
    b, j, h, w = logits.shape
    return torch.softmax(logits.reshape(b, j, h * w), -1).reshape(b, j, h, w)


def jointnet_unaries(
    net: JointNet, channels: Tensor, sizes: list[tuple[int, int]], stride: int
) -> Tensor:
    """The joint network's unaries on the grid: channels (b, 12, H, W) zero-padded, sizes b
    (h, w) -> (b, 14, gh, gw) log(P(joint at the cell) + LOG_EPS), floored as the forests'
    unaries are; log(LOG_EPS) outside each image. Each image runs alone on its own pixels:
    past the first batch norm, a padded batch's zeros are no longer zeros, and the network
    sees about 300 px around each cell."""
    h, w = channels.shape[-2:]
    out = torch.full((len(sizes), NUM_JOINTS, -(-h // stride), -(-w // stride)), LOG_EPS)
    for i, (hi, wi) in enumerate(sizes):
        logits = logits_on_grid(net, channels[i : i + 1, :3, :hi, :wi], stride)
        out[i, :, : logits.shape[2], : logits.shape[3]] = spatial_softmax(logits)[0] + LOG_EPS
    return out.log()
