"""GET /v1/skeleton: the skeleton of every answer (joint names and order, the kinematic tree and
its limbs, each joint's side and the colours ds3d draws them in, the bones, the joint sets), made
from the library's own definitions (ds3d.skeleton, ds3d.viz.overlay) so that the web page and any
other client draw and read the joints without a copy of them. Open without an API key, like the
API's description (ds3d_service.access.rules): it holds no model output."""

from __future__ import annotations

from fastapi import APIRouter

from ds3d import skeleton
from ds3d.viz.overlay import SIDE_COLOURS
from ds3d_service.schemas import JointSet, Skeleton

router = APIRouter()

SKELETON = Skeleton(
    joint_names=list(skeleton.JOINT_NAMES),
    parents=list(skeleton.PARENT),
    limbs=[list(limb) for limb in skeleton.LIMBS],
    sides=list(skeleton.JOINT_SIDES),
    colours={side: list(rgb) for side, rgb in SIDE_COLOURS.items()},
    bone_names=list(skeleton.BONE_NAMES),
    joint_sets={
        name: JointSet(description=skeleton.SET_DESCRIPTIONS[name], joints=list(joints))
        for name, joints in skeleton.JOINT_SETS.items()
    },
)


@router.get("/v1/skeleton", response_model=Skeleton)
async def get_skeleton() -> Skeleton:
    """The 14-joint skeleton: what joints_2d, joints_3d, bone_lengths and joint_set of the
    other answers refer to."""
    return SKELETON
