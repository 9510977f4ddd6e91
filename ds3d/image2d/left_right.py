"""Left and right. The forest cascade labels the limb on the image's left "right" in nearly every
image, as if everyone faced the camera. The joint network, trained on person-centric labels,
knows better: the PSM runs with the cascade's maps as they are and with left and right swapped,
and the better score says whether the person faces the camera (left_right_hypotheses). Without a
joint network, a small CNN on the image around the PSM's torso says it (ds3d.image2d.facing).
Either way left and right are swapped at the end where the person faces away (person_centric),
so results are person-centric like LSP's labels."""

from __future__ import annotations

import torch

from ds3d.image2d.facing import FacingNet, faces_camera_probability
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures, PsmResult, infer
from ds3d.image2d.result import Estimate2D
from ds3d.skeleton import FLIP


def left_right_hypotheses(
    forest: torch.Tensor, net: torch.Tensor, mixtures: PairwiseMixtures, p: EstimatorParams
) -> tuple[torch.Tensor, PsmResult, torch.Tensor]:
    """The PSM on the forests' unaries plus jointnet_weight times the joint network's, with the
    forests' maps taken as they are and with their left and right swapped: the forests label
    the limb on the image's left "right" (as if everyone faced the camera), the network labels
    the person's own, so the better score of the two says whether the person faces the camera.

    forest, net: (B, 14, H, W) log-probability unaries -> (unaries (B, 14, H, W), the PSM's
    result, (B,) P(faces the camera)): the chosen labelling's unaries as a weighted mean,
    (forest + w net) / (1 + w), so that they stay log-probabilities floored at log(LOG_EPS)
    like the forests' (the PSM weighs them by unary_weight * (1 + w): it sees the sum), and
    its MAP pose, both in the forests' labelling (so that person_centric swaps them to the
    person's own where P < 0.5); P is the sigmoid of the score difference of the two
    labellings."""
    b, flip, w = len(forest), list(FLIP), p.jointnet_weight
    both = (torch.cat([forest, forest[:, flip]]) + w * net.repeat(2, 1, 1, 1)) / (1 + w)
    res = infer(both * (p.unary_weight * (1 + w)), mixtures, stride=float(p.stride))
    facing = torch.sigmoid(res.score[:b] - res.score[b:])
    away = facing < 0.5
    rows = torch.arange(b) + b * away.long()

    def forest_labels(t: torch.Tensor) -> torch.Tensor:
        """Rows of the chosen labelling, joints back in the forests' order."""
        t = t[rows]
        return torch.where(away.view(-1, *[1] * (t.ndim - 1)), t[:, flip], t)

    chosen = PsmResult(
        forest_labels(res.joints_2d),
        forest_labels(res.cells),
        res.score[rows],
        forest_labels(res.joint_scores) / (p.unary_weight * (1 + w)),
    )
    return forest_labels(both), chosen, facing


def person_centric(est: Estimate2D) -> Estimate2D:
    """Swap left and right of the images whose person faces away (observer -> person labels)."""
    away = est.facing_camera < 0.5
    flip = list(FLIP)
    return Estimate2D(
        torch.where(away.view(-1, 1, 1), est.joints_2d[:, flip], est.joints_2d),
        torch.where(away.view(-1, 1), est.joint_scores[:, flip], est.joint_scores),
        est.score,
        torch.where(away.view(-1, 1, 1, 1), est.unaries[:, flip], est.unaries),
        est.map_to_image,
        est.scale,
        est.facing_camera,
    )


def facing_probability(
    facing: FacingNet | None,
    channels: torch.Tensor,
    joints: torch.Tensor,
    sizes: list[tuple[int, int]],
) -> torch.Tensor:
    """P(faces the camera) from the facing model around the PSM's pose
    (ds3d.image2d.facing). channels: (B, 12, H, W), zero-padded; joints: (B, 14, 2) (x, y)
    px on them; sizes: B (h, w) -> (B,) float32 (1 for a model without a facing model)."""
    if facing is None:
        return torch.ones(channels.shape[0])
    return faces_camera_probability(facing, channels[:, :3], joints, sizes)
