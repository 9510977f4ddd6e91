"""The 14-joint skeleton used everywhere inside ds3d (LSP order), its kinematic tree,
its limbs, the five joint sets of the paper, and the maps from other skeletons.

Joint order (LSP; "right" is the person's right):
    0 R ankle, 1 R knee, 2 R hip, 3 L hip, 4 L knee, 5 L ankle, 6 R wrist, 7 R elbow,
    8 R shoulder, 9 L shoulder, 10 L elbow, 11 L wrist, 12 neck, 13 head top
"""

from __future__ import annotations

import numpy as np

JOINT_NAMES: tuple[str, ...] = (
    "right_ankle",
    "right_knee",
    "right_hip",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_wrist",
    "right_elbow",
    "right_shoulder",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "neck",
    "head_top",
)
NUM_JOINTS = len(JOINT_NAMES)

R_ANKLE, R_KNEE, R_HIP, L_HIP, L_KNEE, L_ANKLE = range(6)
R_WRIST, R_ELBOW, R_SHOULDER, L_SHOULDER, L_ELBOW, L_WRIST = range(6, 12)
NECK, HEAD_TOP = 12, 13

# Kinematic tree rooted at the neck (the PSM's root): PARENT[i] is the parent of joint i, -1 for
# the root. The hips hang from the neck because LSP has no pelvis joint.
PARENT: tuple[int, ...] = (
    R_KNEE,
    R_HIP,
    NECK,
    NECK,
    L_HIP,
    L_KNEE,
    R_ELBOW,
    R_SHOULDER,
    NECK,
    NECK,
    L_SHOULDER,
    L_ELBOW,
    -1,
    NECK,
)

# Limbs (child, parent): the 13 edges of the kinematic tree; E_a compares their lengths.
LIMBS: tuple[tuple[int, int], ...] = tuple((i, p) for i, p in enumerate(PARENT) if p >= 0)

# The bones of a person's proportions: a tree rooted at the hip midpoint (ROOT, not a joint), as
# (child, parent, scale group). A pose's bone lengths (ds3d.fit.bones) are in this order; the
# lifter estimates one scale per group, the same for left and right.
ROOT = -1
BONES: tuple[tuple[int, int, str], ...] = (
    (R_HIP, ROOT, "pelvis"),
    (L_HIP, ROOT, "pelvis"),
    (NECK, ROOT, "spine"),
    (HEAD_TOP, NECK, "head"),
    (R_SHOULDER, NECK, "collar"),
    (L_SHOULDER, NECK, "collar"),
    (R_ELBOW, R_SHOULDER, "upper_arm"),
    (L_ELBOW, L_SHOULDER, "upper_arm"),
    (R_WRIST, R_ELBOW, "forearm"),
    (L_WRIST, L_ELBOW, "forearm"),
    (R_KNEE, R_HIP, "thigh"),
    (L_KNEE, L_HIP, "thigh"),
    (R_ANKLE, R_KNEE, "shin"),
    (L_ANKLE, L_KNEE, "shin"),
)


def _bone_name(child: int, group: str) -> str:
    side = JOINT_NAMES[child].split("_")[0]
    return f"{side}_{group}" if side in ("left", "right") else group


BONE_NAMES: tuple[str, ...] = tuple(_bone_name(child, group) for child, _, group in BONES)
BONE_GROUPS: tuple[str, ...] = tuple(dict.fromkeys(group for _, _, group in BONES))

# The person's side of each joint: "right", "left", or "centre" for the neck and the head top.
JOINT_SIDES: tuple[str, ...] = tuple(
    name.split("_")[0] if name.startswith(("right_", "left_")) else "centre" for name in JOINT_NAMES
)

# Left/right mirror: FLIP[i] is the joint that i becomes when the image is flipped horizontally.
FLIP: tuple[int, ...] = (5, 4, 3, 2, 1, 0, 11, 10, 9, 8, 7, 6, 12, 13)

# The five joint sets of the paper (fig:features). Neck and head belong to every set that
# contains the upper body, so each set is a connected part of the tree.
JOINT_SETS: dict[str, tuple[int, ...]] = {
    # all 14 joints
    "all": tuple(range(NUM_JOINTS)),
    # upper body, 10: wrists, elbows, shoulders, hips, neck, head
    "up": (
        R_HIP,
        L_HIP,
        R_WRIST,
        R_ELBOW,
        R_SHOULDER,
        L_SHOULDER,
        L_ELBOW,
        L_WRIST,
        NECK,
        HEAD_TOP,
    ),
    # lower body, 6: hips, knees, ankles
    "lw": (R_ANKLE, R_KNEE, R_HIP, L_HIP, L_KNEE, L_ANKLE),
    # the person's left side, 8: left leg and arm, neck, head
    "lt": (L_HIP, L_KNEE, L_ANKLE, L_SHOULDER, L_ELBOW, L_WRIST, NECK, HEAD_TOP),
    # the person's right side, 8: right leg and arm, neck, head
    "rt": (R_ANKLE, R_KNEE, R_HIP, R_WRIST, R_ELBOW, R_SHOULDER, NECK, HEAD_TOP),
}
SET_NAMES: tuple[str, ...] = tuple(JOINT_SETS)
# Each set in words, as the web page names the set a 3D pose was fitted with.
SET_DESCRIPTIONS: dict[str, str] = {
    "all": "all 14 joints",
    "up": "the upper body",
    "lw": "the lower body",
    "lt": "the person's left side",
    "rt": "the person's right side",
}


def joint_set_mask(dtype=np.float32) -> np.ndarray:
    """(5, 14) array, 1 where joint j belongs to set s (rows in SET_NAMES order)."""
    mask = np.zeros((len(SET_NAMES), NUM_JOINTS), dtype=dtype)
    for s, name in enumerate(SET_NAMES):
        mask[s, list(JOINT_SETS[name])] = 1
    return mask


# Human3.6M 17-joint order: 0 pelvis, 1 R hip, 2 R knee, 3 R ankle, 4 L hip, 5 L knee,
# 6 L ankle, 7 spine, 8 thorax, 9 neck/nose, 10 head, 11 L shoulder, 12 L elbow, 13 L wrist,
# 14 R shoulder, 15 R elbow, 16 R wrist. Neck = thorax, head top = head.
H36M17_TO_LSP: tuple[int, ...] = (3, 2, 1, 4, 5, 6, 16, 15, 14, 11, 12, 13, 8, 10)

# CMU BVH (cgspeed conversion, 43 joints + 14 end sites, root "hip") joint names for the 14
# LSP joints. The head top is not a BVH joint ("head" sits at the skull base and has only the
# eyes as children): the last entry names the joint whose frame places it, see
# ds3d.data.cmu.head_top_offset.
CMU_BVH_TO_LSP: tuple[str, ...] = (
    "rFoot",
    "rShin",
    "rThigh",
    "lThigh",
    "lShin",
    "lFoot",
    "rHand",
    "rForeArm",
    "rShldr",
    "lShldr",
    "lForeArm",
    "lHand",
    "neck",
    "head",
)


def hip_midpoint(joints):
    """Root of a pose: the midpoint of the hips. joints: (..., 14, D) -> (..., D)."""
    return (joints[..., R_HIP, :] + joints[..., L_HIP, :]) / 2
