"""Joint angles of the 14-joint skeleton, for animation tools: a rig (a hierarchy of nodes whose
rest offsets come from a person's bone lengths), inverse kinematics from joint positions to a
rotation per node, and forward kinematics back.

World axes: the animation tools' convention, y up: (x, -y, -z) of the camera's (x right, y down,
z away), so that a person facing the camera faces +z. The rest pose is a T-pose facing +z, the
person's right on -x. Every bone (ds3d.skeleton.BONES) is turned by a node of its own: where
several bones leave one joint (the hips, the neck) each leaves from a node at zero offset, so the
rotations place every joint exactly, whatever the angles between those bones, as long as the bones
keep the rig's lengths. A bone's twist about itself is not seen in 14 joints: each node turns its
bone by the least rotation from the rest direction (in its parent's frame), the root by the hip
line and the spine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ds3d.data.bvh import BvhMotion
from ds3d.fit.bones import bone_lengths
from ds3d.skeleton import (
    BONES,
    HEAD_TOP,
    L_ANKLE,
    L_ELBOW,
    L_HIP,
    L_KNEE,
    L_SHOULDER,
    L_WRIST,
    NECK,
    NUM_JOINTS,
    R_ANKLE,
    R_ELBOW,
    R_HIP,
    R_KNEE,
    R_SHOULDER,
    R_WRIST,
    ROOT,
    hip_midpoint,
)

RIGHT, LEFT, UP, DOWN = (-1.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)
# The camera's axes -> the world's (and back: the map is its own inverse).
CAMERA_TO_WORLD = (1.0, -1.0, -1.0)


@dataclass(frozen=True)
class Node:
    """One node of the rig. joint: the skeleton's joint at the node (ROOT: the hip midpoint);
    bone: the BONES index of the bone from the parent's position to the node's, or None for a
    node at its parent's position (where a second bone leaves a joint); rest: that bone's
    direction at rest (world axes). The node's rotation turns the bones of its children."""

    name: str
    parent: int
    joint: int
    bone: int | None = None
    rest: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _bone(child: int) -> int:
    return next(b for b, (c, _, _) in enumerate(BONES) if c == child)


NODES: tuple[Node, ...] = (
    Node("hips", -1, ROOT),
    Node("right_hip", 0, R_HIP, _bone(R_HIP), RIGHT),
    Node("right_knee", 1, R_KNEE, _bone(R_KNEE), DOWN),
    Node("right_ankle", 2, R_ANKLE, _bone(R_ANKLE), DOWN),
    Node("left_hip", 0, L_HIP, _bone(L_HIP), LEFT),
    Node("left_knee", 4, L_KNEE, _bone(L_KNEE), DOWN),
    Node("left_ankle", 5, L_ANKLE, _bone(L_ANKLE), DOWN),
    Node("spine", 0, ROOT),
    Node("neck", 7, NECK, _bone(NECK), UP),
    Node("head", 8, NECK),
    Node("head_top", 9, HEAD_TOP, _bone(HEAD_TOP), UP),
    Node("right_collar", 8, NECK),
    Node("right_shoulder", 11, R_SHOULDER, _bone(R_SHOULDER), RIGHT),
    Node("right_elbow", 12, R_ELBOW, _bone(R_ELBOW), RIGHT),
    Node("right_wrist", 13, R_WRIST, _bone(R_WRIST), RIGHT),
    Node("left_collar", 8, NECK),
    Node("left_shoulder", 15, L_SHOULDER, _bone(L_SHOULDER), LEFT),
    Node("left_elbow", 16, L_ELBOW, _bone(L_ELBOW), LEFT),
    Node("left_wrist", 17, L_WRIST, _bone(L_WRIST), LEFT),
)
# The node at each skeleton joint (where a joint has several, the first: the others are branch
# nodes at zero offset).
JOINT_NODES: tuple[int, ...] = tuple(
    next(n for n, node in enumerate(NODES) if node.joint == j) for j in range(NUM_JOINTS)
)


def _aims() -> tuple[int | None, ...]:
    """Per node, the one child whose bone its rotation aims (None: a leaf, or the root and the
    neck, whose children leave them at zero offset or both ways along the hip line)."""
    children = [[c for c, node in enumerate(NODES) if node.parent == n] for n in range(len(NODES))]
    return tuple(
        kids[0] if n > 0 and len(kids) == 1 and NODES[kids[0]].bone is not None else None
        for n, kids in enumerate(children)
    )


AIMS = _aims()


@dataclass
class Motion:
    """A person's joint angles over F frames: offsets (N, 3) mm, each node's position in its
    parent's frame at rest (NODES order; from the person's bone lengths); root (F, 3) mm, the
    hip midpoint in world axes; rotations (F, N, 3, 3), each node's rotation in its parent's
    frame (the root's in the world's)."""

    offsets: torch.Tensor
    root: torch.Tensor
    rotations: torch.Tensor


def rest_offsets(lengths: torch.Tensor) -> torch.Tensor:
    """(B,) bone lengths mm, BONES order -> (N, 3) rest offsets of the NODES."""
    rest = torch.tensor([node.rest for node in NODES], dtype=lengths.dtype)
    scale = torch.stack(
        [lengths[n.bone] if n.bone is not None else lengths.new_zeros(()) for n in NODES]
    )
    return rest * scale[:, None]


def least_rotation(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The least rotation taking unit vectors source (..., 3) to unit vectors target (..., 3):
    (..., 3, 3). Opposite vectors: the half turn about an axis perpendicular to both."""
    cross = torch.linalg.cross(source, target)
    cos = (source * target).sum(-1)
    zero = torch.zeros_like(cos)
    x, y, z = cross.unbind(-1)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).unflatten(-1, (3, 3))
    eye = torch.eye(3, dtype=source.dtype).expand_as(skew)
    turned = eye + skew + skew @ skew / (1 + cos).clamp_min(1e-12)[..., None, None]
    # a half turn about the axis of source x (x or y, whichever is least along source)
    other = torch.where(
        source[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0])
    ).to(source)
    axis = torch.nn.functional.normalize(torch.linalg.cross(source, other), dim=-1)
    half = 2 * axis[..., :, None] * axis[..., None, :] - eye
    return torch.where((cos < -1 + 1e-9)[..., None, None], half, turned)


def root_frame(joints: torch.Tensor) -> torch.Tensor:
    """(..., 14, 3) world mm -> (..., 3, 3) the hips' rotation: x along the hip line from the
    right hip to the left, y up the spine (its part across the hip line), z = x cross y."""
    x = torch.nn.functional.normalize(joints[..., L_HIP, :] - joints[..., R_HIP, :], dim=-1)
    up = joints[..., NECK, :] - hip_midpoint(joints)
    y = torch.nn.functional.normalize(up - (up * x).sum(-1, keepdim=True) * x, dim=-1)
    return torch.stack([x, y, torch.linalg.cross(x, y)], -1)


def inverse_kinematics(joints: torch.Tensor, lengths: torch.Tensor | None = None) -> Motion:
    """Joint angles of F poses (F, 14, 3) mm, world axes (camera_to_world), float64 best.
    lengths: (B,) the rig's bone lengths (default: the median over the frames of each bone's
    length). Forward kinematics of the result gives back the poses where their bones have the
    rig's lengths (exactly, up to rounding), and otherwise each bone in its own direction."""
    if lengths is None:
        lengths = bone_lengths(joints).median(0).values
    at = torch.cat([joints, hip_midpoint(joints)[:, None]], 1)  # ROOT = -1: the last row
    frames = len(joints)
    eye = torch.eye(3, dtype=joints.dtype).expand(frames, 3, 3)
    local, world = [root_frame(joints)], [root_frame(joints)]
    for n, node in enumerate(NODES[1:], 1):
        parent = world[node.parent]
        aim = AIMS[n]
        if aim is None:
            turn = eye
        else:
            child = NODES[aim]
            direction = torch.nn.functional.normalize(
                at[:, child.joint] - at[:, node.joint], dim=-1
            )
            seen = (parent.transpose(-1, -2) @ direction[..., None])[..., 0]
            turn = least_rotation(
                torch.tensor(child.rest, dtype=joints.dtype).expand_as(seen), seen
            )
        local.append(turn)
        world.append(parent @ turn)
    return Motion(rest_offsets(lengths), hip_midpoint(joints), torch.stack(local, 1))


def camera_motion(joints: np.ndarray) -> Motion:
    """Joint angles of F poses (F, 14, 3) mm in camera coordinates (as answered:
    joints_3d_camera), in float64 (inverse_kinematics of their world axes)."""
    return inverse_kinematics(camera_to_world(torch.from_numpy(np.asarray(joints, np.float64))))


def forward_kinematics(motion: Motion) -> torch.Tensor:
    """The joints (F, 14, 3) mm, world axes, that a Motion places."""
    world: list[torch.Tensor] = []
    where: list[torch.Tensor] = []
    for n, node in enumerate(NODES):
        turn = motion.rotations[:, n]
        if node.parent < 0:
            world.append(turn)
            where.append(motion.root)
            continue
        parent = world[node.parent]
        where.append(where[node.parent] + (parent @ motion.offsets[n].to(parent)[:, None])[..., 0])
        world.append(parent @ turn)
    return torch.stack([where[n] for n in JOINT_NODES], 1)


def camera_to_world(points: torch.Tensor) -> torch.Tensor:
    """(..., 3) camera axes (x right, y down, z away) -> world axes (y up); its own inverse."""
    return points * torch.tensor(CAMERA_TO_WORLD, dtype=points.dtype)


# BVH's channels of the root and of every other node: R = Rz @ Rx @ Ry (ds3d.data.bvh).
ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
CHANNELS = ("Zrotation", "Xrotation", "Yrotation")


def zxy_angles(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) R = Rz(a) Rx(b) Ry(c) -> (..., 3) degrees (a, b, c), b in [-90, 90]."""
    r = rotation
    b = torch.asin(r[..., 2, 1].clamp(-1, 1))
    a = torch.atan2(-r[..., 0, 1], r[..., 1, 1])
    c = torch.atan2(-r[..., 2, 0], r[..., 2, 2])
    return torch.stack([a, b, c], -1) * (180 / math.pi)


def to_bvh(motion: Motion, frame_time: float) -> BvhMotion:
    """A Motion as a BVH file's content: the NODES as joints (an End Site at zero offset after
    each leaf), the root's position and every node's ZXY angles per frame, mm and degrees."""
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[tuple[str, ...]] = []
    index: dict[int, int] = {}
    leaves = {node.parent for node in NODES}
    for n, node in enumerate(NODES):
        index[n] = len(names)
        names.append(node.name)
        parents.append(index.get(node.parent, -1))
        offsets.append(motion.offsets[n].double().numpy())
        channels.append(ROOT_CHANNELS if node.parent < 0 else CHANNELS)
        if n not in leaves:
            names.append(f"{node.name}/End")
            parents.append(index[n])
            offsets.append(np.zeros(3))
            channels.append(())
    angles = zxy_angles(motion.rotations.double()).flatten(1)  # (F, 3 N)
    rows = torch.cat([motion.root.double(), angles], 1).numpy()
    return BvhMotion(
        tuple(names), np.asarray(parents), np.stack(offsets), tuple(channels), frame_time, rows
    )
