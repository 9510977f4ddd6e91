"""ds3d: the dual-source approach to 3D human pose from a single image (Yasin et al., CVPR 2016).

The public API, each name from the module that defines it:

    Pipeline, PipelineConfig        images -> 2D and 3D poses            (ds3d.pipeline)
    PipelineResult, Person          what it answers                      (ds3d.result)
    Lifter, LifterConfig            2D poses -> 3D poses                 (ds3d.lifter)
    LiftResult, LiftedPose          what it answers                      (ds3d.lifter)
    image_input, ImageInput,        inputs checked once, where they      (ds3d.inputs)
    pose_input, PoseInput, MIN_SCORE  enter
    predict, PipelineWorkers        runs over any source, over processes (ds3d.runners)
    read_image, decode_image        images from files and bytes          (ds3d.io.images)
    Ds3dError, InvalidImage, ...    what the library raises              (ds3d.errors)
    JOINT_NAMES, BONE_NAMES         the skeleton's order                 (ds3d.skeleton)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

__version__ = "0.1.0"

# Loaded on first use, so that `import ds3d` (the CLI, the client SDK) stays cheap.
_LAZY = {
    "Pipeline": "ds3d.pipeline",
    "PipelineConfig": "ds3d.pipeline",
    "PipelineResult": "ds3d.result",
    "Person": "ds3d.result",
    "Lifter": "ds3d.lifter",
    "LifterConfig": "ds3d.lifter",
    "LiftResult": "ds3d.lifter",
    "LiftedPose": "ds3d.lifter",
    "ImageInput": "ds3d.inputs",
    "image_input": "ds3d.inputs",
    "PoseInput": "ds3d.inputs",
    "pose_input": "ds3d.inputs",
    "MIN_SCORE": "ds3d.inputs",
    "predict": "ds3d.runners.predict",
    "PipelineWorkers": "ds3d.runners.workers",
    "read_image": "ds3d.io.images",
    "decode_image": "ds3d.io.images",
    "Ds3dError": "ds3d.errors",
    "DataFormatError": "ds3d.errors",
    "ImageTooLarge": "ds3d.errors",
    "InvalidBox": "ds3d.errors",
    "InvalidImage": "ds3d.errors",
    "InvalidPose": "ds3d.errors",
    "JOINT_NAMES": "ds3d.skeleton",
    "BONE_NAMES": "ds3d.skeleton",
}
__all__ = [
    "BONE_NAMES",
    "JOINT_NAMES",
    "MIN_SCORE",
    "DataFormatError",
    "Ds3dError",
    "ImageInput",
    "ImageTooLarge",
    "InvalidBox",
    "InvalidImage",
    "InvalidPose",
    "LiftResult",
    "LiftedPose",
    "Lifter",
    "LifterConfig",
    "Person",
    "Pipeline",
    "PipelineConfig",
    "PipelineResult",
    "PipelineWorkers",
    "PoseInput",
    "__version__",
    "decode_image",
    "image_input",
    "pose_input",
    "predict",
    "read_image",
]

if TYPE_CHECKING:  # the names as the type checker sees them
    from ds3d.errors import (
        DataFormatError,
        Ds3dError,
        ImageTooLarge,
        InvalidBox,
        InvalidImage,
        InvalidPose,
    )
    from ds3d.inputs import MIN_SCORE, ImageInput, PoseInput, image_input, pose_input
    from ds3d.io.images import decode_image, read_image
    from ds3d.lifter import LiftedPose, Lifter, LifterConfig, LiftResult
    from ds3d.pipeline import Pipeline, PipelineConfig
    from ds3d.result import Person, PipelineResult
    from ds3d.runners.predict import predict
    from ds3d.runners.workers import PipelineWorkers
    from ds3d.skeleton import BONE_NAMES, JOINT_NAMES


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'ds3d' has no attribute {name!r}")
