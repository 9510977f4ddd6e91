"""Left and right. The forest cascade labels the limb on the image's left "right" in nearly every
image, as if everyone faced the camera. The joint network, trained on person-centric labels,
knows better: whichever labelling of the cascade's maps, as they are or with left and right
swapped, agrees with its maps says whether the person faces the camera (settle_left_right).
Without a joint network, a small CNN on the image around the PSM's torso says it
(ds3d.image2d.facing).
Either way left and right are swapped at the end where the person faces away (person_centric),
so results are person-centric like LSP's labels."""

from __future__ import annotations

from dataclasses import replace

import torch

from ds3d.image2d.facing import FacingNet, faces_camera_probability
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures, PsmResult, infer
from ds3d.image2d.result import Estimate2D
from ds3d.skeleton import FLIP


def settle_left_right(
    forest: torch.Tensor, net: torch.Tensor, mixtures: PairwiseMixtures, p: EstimatorParams
) -> tuple[torch.Tensor, PsmResult, torch.Tensor]:
    """The forests label the limb on the image's left "right" (as if everyone faced the camera),
    the network labels the person's own: the labelling of the forests' maps (as they are, or
    with left and right swapped) whose joints agree better with the network's says whether the
    person faces the camera, and the PSM runs on it plus jointnet_weight times the network's.

    Agreement of a labelling: the sum over joints of the log-probability that the two put the
    joint on the same cell (sum over cells of the product of their maps' probabilities); P(faces
    the camera) is the sigmoid of the difference between the two labellings' agreements.
    forest, net: (B, 14, H, W) log-probability unaries -> (unaries (B, 14, H, W), the PSM's
    result, (B,) P(faces the camera)): the chosen labelling's unaries as a weighted mean,
    (forest + w net) / (1 + w), so that they stay log-probabilities floored at log(LOG_EPS)
    like the forests' (the PSM weighs them by unary_weight * (1 + w): it sees the sum), and its
    MAP pose, both in the forests' labelling (so that person_centric swaps them to the person's
    own where P < 0.5)."""
    flip, w = list(FLIP), p.jointnet_weight
    facing = torch.sigmoid(_agreement(forest, net) - _agreement(forest[:, flip], net))
    away = facing < 0.5

    def forest_labels(t: torch.Tensor) -> torch.Tensor:
        """t with its joints swapped where the person faces away: from the forests' labelling
        to the network's and back."""
        return torch.where(away.view(-1, *[1] * (t.ndim - 1)), t[:, flip], t)

    unaries = (forest + w * forest_labels(net)) / (1 + w)  # in the forests' labelling
    res = infer(unaries * (p.unary_weight * (1 + w)), mixtures, stride=float(p.stride))
    res = replace(res, joint_scores=res.joint_scores / (p.unary_weight * (1 + w)))  # log-probs
    return unaries, res, facing


def _agreement(forest: torch.Tensor, net: torch.Tensor) -> torch.Tensor:
    """(B, 14, H, W) log-probability maps of two labellings -> (B,) sum over joints of the log
    of their maps' overlap (the probability that both put the joint on the same cell)."""
    both = torch.softmax(forest.flatten(2), -1) * torch.softmax(net.flatten(2), -1)
    return both.sum(-1).clamp_min(1e-30).log().sum(-1)


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
        return channels.new_ones(channels.shape[0])
    return faces_camera_probability(facing, channels[:, :3], joints, sizes)
