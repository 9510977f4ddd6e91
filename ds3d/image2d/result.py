"""The 2D stage's result for a batch (Estimate2D), and how results of parts of a batch combine:
per image the better of two (keep_better), or parts of a batch gathered back into its order
(gather_rows)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ds3d.skeleton import NUM_JOINTS

LOG_EPS = 1e-4  # floor of the probabilities before the log: keeps unaries finite


@dataclass
class Estimate2D:
    """Result of PoseEstimator2D.estimate for B images.

    joints_2d: (B, 14, 2) float32, pixels of the input image.
    joint_scores: (B, 14) float32, each joint's unary log-probability at its MAP cell (before
        joint_cells moved it; PsmResult.joint_scores).
    score: (B,) float32, the PSM score of the chosen scale.
    unaries: (B, 14, h, w) float32 log-probabilities of the chosen scale, padded to a common
        (h, w) with log(LOG_EPS).
    map_to_image: (B, 2, 3) float32 affine map from unary cell (u = column, v = row, 1) to image
        pixels (x, y): image_xy = map_to_image @ (u, v, 1).
    scale: (B,) float32, the working scale chosen (working px per image px, mean of x and y).
    facing_camera: (B,) float32, the probability that the person faces the camera: with a joint
        network, from how much better the cascade's labelling agrees with the network's maps
        than the swapped one (settle_left_right); else the facing model's (1 for models with
        neither); below 0.5, left and right were swapped.
    timings: seconds per step (features, traversal, jointnet, psm, total).
    """

    joints_2d: torch.Tensor
    joint_scores: torch.Tensor
    score: torch.Tensor
    unaries: torch.Tensor
    map_to_image: torch.Tensor
    scale: torch.Tensor
    facing_camera: torch.Tensor
    timings: dict[str, float] = field(default_factory=dict)

    def rows(self, index: torch.Tensor) -> Estimate2D:
        """The images `index` (K,) long, in that order, with the same timings."""
        return Estimate2D(
            self.joints_2d[index],
            self.joint_scores[index],
            self.score[index],
            self.unaries[index],
            self.map_to_image[index],
            self.scale[index],
            self.facing_camera[index],
            dict(self.timings),
        )

    def sample_unaries(self, points: torch.Tensor) -> torch.Tensor:
        """Unary log-probs at image points, bilinear on the unary grid.

        points: (B, K, 14, 2) float32 image pixels -> (B, K, 14) float32; points outside the
        map get log(LOG_EPS).
        """
        b, k = points.shape[:2]
        a = self.map_to_image[:, :, :2]  # (B, 2, 2), diagonal
        t = self.map_to_image[:, :, 2]  # (B, 2)
        uv = (points - t[:, None, None, :]) / torch.diagonal(a, dim1=1, dim2=2)[:, None, None, :]
        h, w = self.unaries.shape[-2:]
        # grid_sample wants (x, y) in [-1, 1] with align_corners=True: -1 = cell 0.
        norm = torch.stack([uv[..., 0] / max(w - 1, 1), uv[..., 1] / max(h - 1, 1)], -1) * 2 - 1
        # One sampling grid per joint: treat joints as the batch of (1-channel) maps.
        maps = self.unaries.reshape(b * NUM_JOINTS, 1, h, w)
        grid = norm.permute(0, 2, 1, 3).reshape(b * NUM_JOINTS, k, 1, 2)
        out = torch.nn.functional.grid_sample(
            maps - np.log(LOG_EPS), grid, mode="bilinear", padding_mode="zeros", align_corners=True
        )  # shifted so that outside (zero padding) means log(LOG_EPS)
        return (out.reshape(b, NUM_JOINTS, k).permute(0, 2, 1) + np.log(LOG_EPS)).contiguous()


def pad_maps(maps: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Pad (B, 14, h0, w0) log-prob maps to (B, 14, h, w) with log(LOG_EPS)."""
    out = maps.new_full((*maps.shape[:2], h, w), float(np.log(LOG_EPS)))
    out[:, :, : maps.shape[2], : maps.shape[3]] = maps
    return out


def keep_better(a: Estimate2D, b: Estimate2D) -> Estimate2D:
    """Per image, the estimate with the higher PSM score."""
    take_b = b.score > a.score
    h = max(a.unaries.shape[2], b.unaries.shape[2])
    w = max(a.unaries.shape[3], b.unaries.shape[3])
    sel = take_b.view(-1, 1, 1, 1)
    return Estimate2D(
        torch.where(take_b.view(-1, 1, 1), b.joints_2d, a.joints_2d),
        torch.where(take_b.view(-1, 1), b.joint_scores, a.joint_scores),
        torch.where(take_b, b.score, a.score),
        torch.where(sel, pad_maps(b.unaries, h, w), pad_maps(a.unaries, h, w)),
        torch.where(take_b.view(-1, 1, 1), b.map_to_image, a.map_to_image),
        torch.where(take_b, b.scale, a.scale),
        torch.where(take_b, b.facing_camera, a.facing_camera),
    )


def gather_rows(parts: list[tuple[torch.Tensor, Estimate2D]], b: int) -> Estimate2D:
    """One Estimate2D of b images from parts that each hold some of them: (rows (n,) long,
    the estimate of those n images). Unary maps are padded to a common size; the timings are
    the sums of the parts'."""
    h = max(part.unaries.shape[2] for _, part in parts)
    w = max(part.unaries.shape[3] for _, part in parts)
    rows = torch.cat([r for r, _ in parts])
    order = torch.empty_like(rows)
    order[rows] = torch.arange(b)  # where each image's row lies in the concatenation

    def cat(get):
        return torch.cat([get(part) for _, part in parts])[order]

    timings: dict[str, float] = {}
    for _, part in parts:
        for step, seconds in part.timings.items():
            timings[step] = timings.get(step, 0.0) + seconds
    return Estimate2D(
        cat(lambda e: e.joints_2d),
        cat(lambda e: e.joint_scores),
        cat(lambda e: e.score),
        cat(lambda e: pad_maps(e.unaries, h, w)),
        cat(lambda e: e.map_to_image),
        cat(lambda e: e.scale),
        cat(lambda e: e.facing_camera),
        timings,
    )
