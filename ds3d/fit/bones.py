"""A person's proportions: bone vectors, bone lengths, and poses with scaled bones.

The bones are ds3d.skeleton.BONES, a tree rooted at the hip midpoint. Scaling a bone moves every
joint below it, so a pose with scaled bones is a linear map of the pose, joint by joint:
X' = root + sum over the bones b on the path to joint j of g_b (X_child(b) - X_parent(b)),
which keeps the root where it was and every bone's direction.
"""

from __future__ import annotations

import numpy as np
import torch

from ds3d.skeleton import BONE_GROUPS, BONES, L_HIP, NUM_JOINTS, R_HIP, ROOT


def _matrices() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """root (14,): the root as a mix of joints; bone (B, 14): bone vectors from joints; path
    (14, B): 1 where bone b lies between the root and joint j; group (B, G): one-hot."""
    root = np.zeros(NUM_JOINTS, np.float32)
    root[[R_HIP, L_HIP]] = 0.5
    bone = np.zeros((len(BONES), NUM_JOINTS), np.float32)
    group = np.zeros((len(BONES), len(BONE_GROUPS)), np.float32)
    parent_bone = {}
    for b, (child, parent, name) in enumerate(BONES):
        bone[b, child] += 1
        bone[b] -= root if parent == ROOT else np.eye(NUM_JOINTS, dtype=np.float32)[parent]
        group[b, BONE_GROUPS.index(name)] = 1
        parent_bone[child] = (b, parent)
    path = np.zeros((NUM_JOINTS, len(BONES)), np.float32)
    for joint in range(NUM_JOINTS):
        node = joint
        while node != ROOT:
            b, node = parent_bone[node]
            path[joint, b] = 1
    return root, bone, path, group


ROOT_MIX, BONE_MATRIX, PATH, GROUP = (torch.from_numpy(m) for m in _matrices())
PATH_GROUP = PATH[..., None] * GROUP  # (14, B, G): 1 where a bone of group g leads to joint j

# How much each bone group varies between people: the standard deviation over the Human3.6M
# training subjects (S1, S5-S9) of the log of each subject's median group length, BONE_GROUPS
# order (pelvis, spine, head, collar, upper arm, forearm, thigh, shin). The prior on a person's
# scales is relative to these: a head or a collar may differ more than a forearm.
GROUP_LOG_SD = torch.tensor([0.072, 0.026, 0.115, 0.096, 0.044, 0.017, 0.042, 0.026])


def group_spread(rms: float = 1.0) -> torch.Tensor:
    """(G,) each bone group's spread of log scales, BONE_GROUPS order: GROUP_LOG_SD rescaled to an
    RMS of `rms` (one: the units of the 3D fit's prior on a person's scales)."""
    return GROUP_LOG_SD * (rms / GROUP_LOG_SD.pow(2).mean().sqrt())


def bone_vectors(poses: torch.Tensor) -> torch.Tensor:
    """(..., 14, 3) mm -> (..., B, 3) mm, child minus parent, in BONES order."""
    return BONE_MATRIX.to(poses) @ poses


def bone_lengths(poses: torch.Tensor) -> torch.Tensor:
    """(..., 14, 3) mm -> (..., B) mm, in BONES order."""
    return bone_vectors(poses).norm(dim=-1)


def bone_scales(group_scales: torch.Tensor) -> torch.Tensor:
    """(..., G) one scale per group (BONE_GROUPS) -> (..., B) one per bone."""
    return group_scales @ GROUP.to(group_scales).T


def scaling_map(group_scales: torch.Tensor) -> torch.Tensor:
    """(..., G) scales -> (..., 14, 14) A, with A @ pose the pose with its bones scaled."""
    return bone_scaling_map(bone_scales(group_scales))


def bone_scaling_map(scales: torch.Tensor) -> torch.Tensor:
    """(..., B) one scale per bone -> (..., 14, 14) A, with A @ pose the pose with its bones
    scaled."""
    mix = ROOT_MIX.to(scales).expand(NUM_JOINTS, NUM_JOINTS)
    return mix + (PATH.to(scales) * scales[..., None, :]) @ BONE_MATRIX.to(scales)


def with_bone_lengths(poses: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Poses (..., 14, 3) mm with each bone's direction kept and its length set to lengths
    (..., B) mm (the two hip bones' alike: the root is their midpoint); the root stays."""
    return bone_scaling_map(lengths / bone_lengths(poses).clamp_min(1e-3)) @ poses


def scale_derivatives(poses: torch.Tensor, group_scales: torch.Tensor) -> torch.Tensor:
    """d (scaled pose) / d (log group scale): poses (..., 14, 3) unscaled, group_scales (..., G).
    Returns (..., 14, 3, G)."""
    scaled_bones = bone_scales(group_scales)[..., None] * bone_vectors(poses)  # (..., B, 3)
    # (14 * G, B) @ (..., B, 3) -> (..., 14, G, 3)
    per_group = PATH_GROUP.to(poses).transpose(1, 2).flatten(0, 1) @ scaled_bones
    return per_group.unflatten(-2, (PATH_GROUP.shape[0], PATH_GROUP.shape[2])).transpose(-1, -2)
