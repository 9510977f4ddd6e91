"""Does the person face the camera? A small CNN on the image around the torso.

The cascade cannot tell left from right when a person turns their back: it labels the limb on
the image's left "right" in nearly every image (docs/RESULTS.md). What tells is mostly the head (a
face or the back of a head) and the torso, seen together. The facing model reads a
CROP x CROP window of the Lab channels at the working scale (a person spans about 100 px, so
the window holds the head, the torso and the thighs), centred a quarter of the way from the
neck to the hips' midpoint: a centre that does not depend on the left/right labels it has to
judge. On the held-out images it replaced a forest on a pose-aligned descriptor of the same
channels (docs/tuning.md, what did not help).

Facing the camera is mirror-invariant (a mirrored person who faces the camera still does, with
left and right relabelled), so training flips every crop at random and keeps its label.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ds3d.skeleton import L_HIP, NECK, R_HIP

CROP = 64  # px at the working scale
# (right chain, left chain) of the arms from the shoulder and of the legs from the hip, for the
# observer-centric relabelling of EstimatorParams.observer_labels (ds3d.training.images).
CHAINS = (((8, 7, 6), (9, 10, 11)), ((2, 1, 0), (3, 4, 5)))


def observer_order(joints: torch.Tensor) -> torch.Tensor:
    """(B, 14, 2) poses (x, y) -> (B, 14) long: the joint order that relabels each arm (leg)
    pair so that the one whose shoulder (hip) has the smaller x is the right one."""
    order = torch.arange(joints.shape[-2], device=joints.device).repeat(len(joints), 1)
    for right, left in CHAINS:
        swap = joints[:, right[0], 0] > joints[:, left[0], 0]  # (B,)
        for r, k in zip(right, left, strict=True):
            order[swap, r], order[swap, k] = k, r
    return order


class FacingNet(nn.Module):
    """(B, 3, CROP, CROP) Lab / 100 -> (B,) logit of "faces the camera". Four 3 x 3 conv
    blocks with batch norm, three 2 x 2 max pools, global average pooling: 113k parameters,
    about 25 M multiply-adds per window."""

    def __init__(self):
        super().__init__()

        def block(cin: int, cout: int) -> list[nn.Module]:
            return [nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU()]

        self.layers = nn.Sequential(
            *block(3, 24), nn.MaxPool2d(2), *block(24, 48), nn.MaxPool2d(2),
            *block(48, 64), nn.MaxPool2d(2), *block(64, 128),
            nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Dropout(0.3), nn.Linear(128, 1),
        )  # fmt: skip

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        return self.layers(crops)[:, 0]


def crop_centre(joints: torch.Tensor) -> torch.Tensor:
    """(B, 14, 2) poses (x, y) px, any left/right labelling -> (B, 2) window centres (x, y) px."""
    neck = joints[:, NECK]
    return neck + 0.25 * ((joints[:, R_HIP] + joints[:, L_HIP]) / 2 - neck)


def crop(
    lab: torch.Tensor,
    centre: torch.Tensor,
    zoom: torch.Tensor | None = None,
    flip: torch.Tensor | None = None,
    size: int = CROP,
) -> torch.Tensor:
    """Windows of size x size px, bilinear, zeros outside the image.

    lab: (B, 3, H, W) float32; centre: (B, 2) (x, y) px; zoom: None or (B,) image px per window
    px (training jitters the scale); flip: None or (B,) bool, mirror the window
    -> (B, 3, size, size) float32. Output pixel k reads centre + (k - (size - 1) / 2) * zoom.
    """
    b, _, h, w = lab.shape
    step = lab.new_ones(b) if zoom is None else zoom
    sx = step if flip is None else torch.where(flip, -step, step)
    k = torch.arange(size, dtype=torch.float32, device=lab.device) - (size - 1) / 2
    xs = centre[:, 0, None] + k[None] * sx[:, None]  # (B, size)
    ys = centre[:, 1, None] + k[None] * step[:, None]
    grid = torch.stack(
        [
            (xs / max(w - 1, 1) * 2 - 1)[:, None, :].expand(b, size, size),
            (ys / max(h - 1, 1) * 2 - 1)[:, :, None].expand(b, size, size),
        ],
        -1,
    )
    return F.grid_sample(lab, grid, mode="bilinear", align_corners=True)


def faces_camera_probability(
    net: FacingNet, lab: torch.Tensor, joints: torch.Tensor, sizes: list[tuple[int, int]]
) -> torch.Tensor:
    """P(faces the camera) per person: the mean over the window and its mirror image, so the
    answer is mirror-invariant as the truth is (+0.2 point PCK on the held-out images).

    lab: (B, 3, H, W) Lab / 100 of a zero-padded batch; joints: (B, 14, 2) (x, y) px on it;
    sizes: B (h, w), each image's own size -> (B,) float32. Each image is cropped from its own
    pixels and run alone, so a result does not depend on the batch it came in.
    """
    centres = crop_centre(joints.float())
    out = lab.new_empty(len(sizes))
    with torch.no_grad():
        for i, (h, w) in enumerate(sizes):
            window = crop(lab[i : i + 1, :, :h, :w], centres[i : i + 1])
            out[i] = torch.sigmoid(net(torch.cat([window, window.flip(-1)]))).mean()
    return out
