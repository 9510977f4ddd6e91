"""Request and response bodies of the HTTP API (pydantic; they make the OpenAPI at /docs).

Units: pixels for 2D joints, millimetres for 3D joints; joints in LSP order (`joint_names`).
Non-finite numbers (NaN, Infinity, which Python's JSON parser accepts) are refused with 422.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict

import ds3d.lifter
import ds3d.result
from ds3d.fit.camera import ASSUMED_FOV_DEG, quaternion
from ds3d.inputs import MAX_COORDINATE_PX, MIN_FOCAL_PX
from ds3d.kinematics import NODES, Motion, camera_motion
from ds3d.skeleton import NUM_JOINTS

Point2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Point3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Quaternion = Annotated[list[float], Field(min_length=4, max_length=4)]
# What the library takes (ds3d.inputs), said in the schema: coordinates and camera entries within
# MAX_COORDINATE_PX, focal lengths of at least MIN_FOCAL_PX, at least two joints visible. Numbers
# and flags are strict, as JSON Schema's types are: true is not the number 1, nor 1 a boolean.
Coordinate = Annotated[float, Strict(), Field(ge=-MAX_COORDINATE_PX, le=MAX_COORDINATE_PX)]
Focal = Annotated[float, Strict(), Field(ge=MIN_FOCAL_PX, le=MAX_COORDINATE_PX)]
Flag = Annotated[bool, Strict()]
InputPoint2 = Annotated[list[Coordinate], Field(min_length=2, max_length=2)]
Intrinsics = tuple[
    tuple[Focal, Coordinate, Coordinate],
    tuple[Coordinate, Focal, Coordinate],
    tuple[Coordinate, Coordinate, Coordinate],
]
# A person box's corners x0, y0, x1, y1 px, as earlier clients send /v1/pose's `bbox`: its rules
# (x1 > x0, y1 > y0, overlapping the image) are beyond a schema, and ds3d.inputs checks them.
Corners = tuple[Coordinate, Coordinate, Coordinate, Coordinate]
MIN_VISIBLE = 2  # ds3d.inputs.visibility_batch
# A PersonBox's sides, as fractions of the image's: from a millionth (smaller ones could round
# to no area when made pixels; ds3d.inputs widens a box under a pixel anyway) to twice the image.
MIN_BOX_FRACTION = 1e-6
MAX_BOX_FRACTION = 2.0
Centre = Annotated[float, Strict(), Field(ge=0.0, le=1.0)]
Side = Annotated[float, Strict(), Field(ge=MIN_BOX_FRACTION, le=MAX_BOX_FRACTION)]


class _Strict(BaseModel):
    model_config = ConfigDict(allow_inf_nan=False, extra="forbid")


class LiftItem(_Strict):
    joints_2d: Annotated[list[InputPoint2], Field(min_length=NUM_JOINTS, max_length=NUM_JOINTS)] = (
        Field(description="14 joints (LSP order) as [x, y] pixels")
    )
    intrinsics: Intrinsics | None = Field(
        None, description="3x3 camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]; omitted: unknown"
    )
    visible: Annotated[list[Flag], Field(min_length=NUM_JOINTS, max_length=NUM_JOINTS)] | None = (
        Field(
            None,
            description="14 flags, false for a joint whose 2D position is a guess; at least "
            f"{MIN_VISIBLE} true",
            json_schema_extra={"contains": {"const": True}, "minContains": MIN_VISIBLE},
        )
    )


class PersonBox(_Strict):
    """Where the person is in /v1/pose's image, as fractions of its width and height (0 the
    left or top edge, 1 the right or bottom; YOLO's convention): its centre on the image, so
    that the box overlaps it, and its sides more than zero, up to twice the image's (a photo
    that cuts the person off, with the box of all of them)."""

    cx: Centre = Field(description="the box's centre, fraction of the image's width from its left")
    cy: Centre = Field(description="the box's centre, fraction of the image's height from its top")
    width: Side = Field(description="the box's width, fraction of the image's width")
    height: Side = Field(description="the box's height, fraction of the image's height")

    def corners(self, width: int, height: int) -> np.ndarray:
        """The box's corners x0, y0, x1, y1 in px of an image of width x height px: (4,)
        float64 (ds3d.inputs.checked_box's input)."""
        centre = np.array([self.cx, self.cy, self.cx, self.cy])
        half = np.array([-self.width, -self.height, self.width, self.height]) / 2
        return (centre + half) * np.array([width, height, width, height], np.float64)


class LiftRequest(_Strict):
    items: list[LiftItem] = Field(min_length=1, description="poses to lift, answered in order")


class LiftedPose(BaseModel):
    """One pose lifted, as the API answers it (ds3d.lifter.LiftedPose)."""

    joints_3d: list[Point3] = Field(description="14 joints as [x, y, z] millimetres")
    bone_lengths: list[float] = Field(
        description="the person's 14 bone lengths, millimetres, in bone_names order: estimated"
        " from the 2D pose, held near the pose database's proportions"
    )
    joint_set: str = Field(description="the joint set the 3D pose was fitted with")
    energy: float = Field(description="the fit's final energy (lower fits better)")
    root_position: Point3 | None = Field(
        None,
        description="with intrinsics, the hip midpoint as [x, y, z] millimetres in the camera's"
        " coordinates (x right, y down, z away from the camera): joints_3d + root_position are"
        " the joints there",
    )

    @classmethod
    def of(cls, pose: ds3d.lifter.LiftedPose) -> LiftedPose:
        """The library's lifted pose as the API answers it."""
        return cls.model_validate(pose.to_json())


class LiftResponse(BaseModel):
    items: list[LiftedPose]
    joint_names: list[str]
    bone_names: list[str] = Field(description="bone_lengths' order: child joint's side and bone")
    model: str = Field(description="id of the model that answered")
    timings_ms: dict[str, float] = Field(
        description="queue wait, per-stage model time (of the batches the items ran in), total"
    )


class JointAngles(BaseModel):
    """A person's joint angles for animation tools (ds3d.kinematics): the ds3d skeleton as a
    hierarchy of nodes, every bone turned by a node of its own; world axes y up (the camera's
    x, -y, -z: a person facing the camera faces +z), a T-pose facing +z at rest, millimetres.
    Forward kinematics of these places the joints at joints_3d_camera (in world axes)."""

    nodes: list[str] = Field(description="the nodes, every parent before its children")
    parents: list[int] = Field(description="per node, its parent's index; -1 for the root")
    offsets: list[Point3] = Field(
        description="per node, its position in its parent's frame at rest, millimetres (from"
        " the person's bone lengths)"
    )
    root: Point3 = Field(description="the root (the hip midpoint), millimetres, world axes")
    rotations: list[Quaternion] = Field(
        description="per node, its rotation in its parent's frame (the root's in the world's)"
        " as a unit quaternion [w, x, y, z]"
    )

    @classmethod
    def of(cls, motion: Motion) -> JointAngles:
        """The first frame of a Motion (ds3d.kinematics)."""
        return cls(
            nodes=[node.name for node in NODES],
            parents=[node.parent for node in NODES],
            offsets=motion.offsets.tolist(),
            root=motion.root[0].tolist(),
            rotations=quaternion(motion.rotations[0]).tolist(),
        )


class Person(BaseModel):
    box: list[float] = Field(
        description="[x0, y0, x1, y1] pixels, the box of the joints (past the image's edges"
        " where the photo cuts the person off)"
    )
    score: float = Field(description="probability in [0, 1] that this is a person")
    joints_2d: list[Point2] = Field(
        description="14 joints as [x, y] pixels of the input image; a joint the photo cuts off"
        " lies past its edges (negative, or beyond its width or height)"
    )
    joints_3d: list[Point3] = Field(
        description="14 joints as [x, y, z] millimetres, camera-oriented (x right, y down, z away"
        " from the camera), root at the hip midpoint"
    )
    root_position: Point3 = Field(
        description="the hip midpoint as [x, y, z] millimetres in the camera's coordinates: where"
        " the person stands, placed with focal length focal_px"
    )
    joints_3d_camera: list[Point3] = Field(
        description="14 joints as [x, y, z] millimetres in the camera's coordinates: joints_3d +"
        " root_position"
    )
    focal_px: float = Field(
        description="the focal length, pixels, of the camera the people are placed by: the"
        " intrinsics' or focal_px given, or an assumed one"
    )
    focal_assumed: bool = Field(
        description=f"true when focal_px was assumed (a {ASSUMED_FOV_DEG:g}-degree field of view"
        " across the image's longer side): depths then scale with the true focal length"
    )
    confidence: list[float] = Field(
        description="per joint, the probability in [0, 1] that it lies within PCK@0.2 of the "
        "truth (0.2 times the torso's diagonal), calibrated on held-out LSP images"
    )
    facing_camera: float = Field(
        description="probability that the person faces the camera; left and right are the"
        " person's own, and below 0.5 they were swapped: near 0.5 they are a guess"
    )
    joint_set: str
    angles: JointAngles | None = Field(
        None, description="with angles=true, the joint angles for animation tools"
    )

    @classmethod
    def of(cls, person: ds3d.result.Person, angles: bool = False) -> Person:
        """The library's person (ds3d.result.Person) as the API answers it, with its joint
        angles when asked."""
        answer = cls.model_validate(person.to_json())
        if angles:
            answer.angles = JointAngles.of(camera_motion(person.joints_3d_camera[None]))
        return answer


class PoseResponse(Person):
    """The best person (without people=all): today's shape, with its box and score."""

    person_found: bool = Field(
        description="false when nobody in the image scored min_score: the pose is then the"
        " likeliest candidate's, and probably not a person's (true when a bbox was given)"
    )
    joint_names: list[str]
    model: str
    timings_ms: dict[str, float]


class PeopleResponse(BaseModel):
    """Every person found (people=all), best first; none for an image without people."""

    people: list[Person]
    joint_names: list[str]
    model: str
    timings_ms: dict[str, float]


Colour = tuple[
    Annotated[int, Field(ge=0, le=255)],
    Annotated[int, Field(ge=0, le=255)],
    Annotated[int, Field(ge=0, le=255)],
]


class JointSet(BaseModel):
    description: str = Field(description="the set in words")
    joints: list[int] = Field(description="its joints, as indices into joint_names")


class Skeleton(BaseModel):
    """The 14-joint skeleton of every answer, from the library's definitions (ds3d.skeleton)."""

    joint_names: list[str] = Field(
        description="the joints in the order of every joints_2d, joints_3d and confidence (LSP"
        " order; right and left are the person's own)"
    )
    parents: list[int] = Field(
        description="per joint, the joint it hangs from in the kinematic tree; -1 for the root"
        " (the neck)"
    )
    limbs: list[tuple[int, int]] = Field(
        description="the edges of the tree, as [child, parent] indices into joint_names"
    )
    sides: list[Literal["right", "left", "centre"]] = Field(
        description="per joint, the person's side (centre: the neck and the head top)"
    )
    colours: dict[str, Colour] = Field(
        description="RGB of the limbs ending at a joint of each side, as ds3d draws them"
    )
    bone_names: list[str] = Field(description="the order of /v1/lift's bone_lengths")
    joint_sets: dict[str, JointSet] = Field(
        description="the paper's five joint sets, by the name an answer's joint_set gives"
    )


class ErrorDetail(BaseModel):
    code: str = Field(description="stable machine-readable code, e.g. invalid_image")
    message: str
    details: list[dict] | None = None


class ErrorResponse(BaseModel):
    error: ErrorDetail


class Health(BaseModel):
    status: str
    model: str | None = None
    queue_depth: int | None = None
    pose_available: bool | None = None


# The error answers of the model routes, as their OpenAPI lists them.
ERROR_RESPONSES: dict[int | str, dict[str, object]] = {
    status: {"model": ErrorResponse, "description": what}
    for status, what in {
        400: "a body that cannot be parsed as its content type says (e.g. broken multipart)",
        413: "body or image over the size limit",
        415: "unsupported content type",
        422: "invalid input (malformed JSON, wrong joint count, non-finite numbers, bad image)",
        429: "over this caller's request rate or queue share (see Retry-After)",
        431: "request head over max_header_bytes",
        500: "an unexpected failure of the model on this request",
        503: "queue full, shutting down, or model unavailable (see Retry-After)",
        504: "not answered before the request deadline",
    }.items()
}
