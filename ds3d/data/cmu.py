"""CMU motion capture (cgspeed-style BVH) as 14-joint poses in Human3.6M's world convention.

The paper maps the CMU skeleton to the target skeleton by linear regression. Here the mapping is
bone-length retargeting instead: each pose keeps its bone directions and takes the median bone
lengths of the Human3.6M training subjects, so both mocap sources share one set of proportions
(`python -m ds3d.data.cmu` prints the lengths before and after, the pose count and load time).

Conventions of the files in data_root()/"cmu_bvh" (all 22 share one 57-joint skeleton):
- Units: the data README says inches, but the skeleton only makes sense in centimetres. The
  upper arm is 28.2 units, the forearm 23.7, the shin 45.4, the eyes 7.8 apart, the standing
  ankle-to-skull-base height 141, and the ankles rest about 6 units above the floor (y = 0): as
  centimetres that is a 1.7 m person (Human3.6M medians: upper arm 279 mm, forearm 249 mm, shin
  442 mm); as inches it would be 3.6 m tall with 20 cm between the eyes. So 1 unit = 10 mm.
- Axes: y up, the rest pose faces +z. Human3.6M's world is z up, so (x, y, z) -> (x, -z, y),
  a +90 degree rotation about x (a rotation, so the result stays right-handed).
- Frame rate: 120 Hz; poses are subsampled to `fps` (the paper uses 30 Hz).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ds3d.data.bvh import BvhMotion, global_transforms, read_bvh
from ds3d.errors import DataFormatError
from ds3d.skeleton import (
    CMU_BVH_TO_LSP,
    H36M17_TO_LSP,
    HEAD_TOP,
    L_ANKLE,
    L_ELBOW,
    L_HIP,
    L_KNEE,
    L_SHOULDER,
    L_WRIST,
    NECK,
    R_ANKLE,
    R_ELBOW,
    R_HIP,
    R_KNEE,
    R_SHOULDER,
    R_WRIST,
    hip_midpoint,
)
from ds3d.util.paths import data_root
from ds3d.util.progress import progress

CMU_UNIT_MM = 10.0  # millimetres per file unit (see the module docstring for the evidence)
# Rows map file axes to Human3.6M axes: new = _Y_UP_TO_Z_UP @ old, i.e. (x, y, z) -> (x, -z, y).
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

H36M_TRAIN_SUBJECTS: tuple[str, ...] = ("S1", "S5", "S6", "S7", "S8", "S9")

PELVIS = -1  # the hip midpoint, root of the retargeting tree (not one of the 14 joints)
# The 13 bones whose lengths retargeting sets, as (joint, parent), parents before children.
# "hip_width" is special: the pelvis stays the midpoint of the hips, each hip moves half of it.
BONES: tuple[tuple[int, int], ...] = (
    (R_HIP, L_HIP),
    (R_KNEE, R_HIP), (R_ANKLE, R_KNEE), (L_KNEE, L_HIP), (L_ANKLE, L_KNEE),
    (NECK, PELVIS),
    (R_SHOULDER, NECK), (R_ELBOW, R_SHOULDER), (R_WRIST, R_ELBOW),
    (L_SHOULDER, NECK), (L_ELBOW, L_SHOULDER), (L_WRIST, L_ELBOW),
    (HEAD_TOP, NECK),
)  # fmt: skip
BONE_NAMES: tuple[str, ...] = (
    "hip_width",
    "right_thigh", "right_shin", "left_thigh", "left_shin",
    "spine",
    "right_collar", "right_upper_arm", "right_forearm",
    "left_collar", "left_upper_arm", "left_forearm",
    "head",
)  # fmt: skip


def _joint_or_pelvis(poses: np.ndarray, j: int) -> np.ndarray:
    return hip_midpoint(poses) if j == PELVIS else poses[..., j, :]


def bone_lengths(poses: np.ndarray) -> np.ndarray:
    """poses: (N, 14, 3) -> (N, 13) lengths of BONES (order BONE_NAMES), same units."""
    return np.stack(
        [np.linalg.norm(poses[..., j, :] - _joint_or_pelvis(poses, p), axis=-1) for j, p in BONES],
        axis=-1,
    )


def retarget_bone_lengths(poses: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Give every pose the bone lengths `lengths`, keeping each bone's direction.

    poses: (N, 14, 3) float, any length unit; lengths: (13,) in that unit, order BONE_NAMES.
    Walks the tree rooted at the hip midpoint (pelvis -> hips -> knees -> ankles; pelvis ->
    neck -> shoulders -> elbows -> wrists; neck -> head top), so the pelvis stays in place and
    each joint moves with its parent. A zero-length bone stays zero (it has no direction).
    Returns (N, 14, 3) in poses' dtype.
    """
    lengths = np.asarray(lengths, dtype=np.float64)
    if lengths.shape != (len(BONES),):
        raise ValueError(f"lengths must have shape ({len(BONES)},), got {lengths.shape}")
    src = np.asarray(poses, dtype=np.float64)
    out = src.copy()

    def direction(j: int, p: int) -> np.ndarray:
        v = src[..., j, :] - _joint_or_pelvis(src, p)
        norm = np.linalg.norm(v, axis=-1, keepdims=True)
        return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)

    pelvis = hip_midpoint(src)
    half_width = direction(R_HIP, L_HIP) * (lengths[0] / 2)
    out[..., R_HIP, :] = pelvis + half_width
    out[..., L_HIP, :] = pelvis - half_width
    for (j, p), length in zip(BONES[1:], lengths[1:], strict=True):
        out[..., j, :] = _joint_or_pelvis(out, p) + direction(j, p) * length
    return out.astype(np.asarray(poses).dtype)


def h36m_reference_bone_lengths(
    subjects: tuple[str, ...] = H36M_TRAIN_SUBJECTS, path: Path | None = None
) -> np.ndarray:
    """(13,) float64 mm: the median of each bone's length over every pose of `subjects`
    (default the Human3.6M training subjects; never S11, the test subject).
    path: the poses npz, default data_root()/"h36m/poses_3d_17j.npz"."""
    path = Path(path or data_root() / "h36m" / "poses_3d_17j.npz").resolve()
    return _median_bone_lengths(tuple(subjects), path).copy()


@functools.lru_cache(maxsize=4)  # reading the archive takes about a second
def _median_bone_lengths(subjects: tuple[str, ...], path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataFormatError(f"Human3.6M poses not found at {path} (set $DS3D_DATA)")
    with np.load(path) as archive:
        keys = [k for k in archive.files if k.split("/")[0] in subjects]
        if not keys:
            raise DataFormatError(f"{path}: no sequence of subjects {subjects}")
        lengths = [bone_lengths(archive[k][:, H36M17_TO_LSP].astype(np.float64)) for k in keys]
    return np.median(np.concatenate(lengths), axis=0)


def head_top_offset(motion: BvhMotion) -> np.ndarray:
    """(3,) head top in the frame of the "head" joint, file units.

    The skeleton has no head-top joint: "head" sits at the skull base and its only children are
    the eyes. The crown is taken above the eyes' midpoint, along the head's up axis (+y, the
    rest pose's up), by as much as the eyes sit above the head joint. With this choice the
    neck -> head top direction leans a median 19.6 degrees from the pelvis -> neck direction
    over the CMU clips, against 18.5 degrees for pelvis -> thorax -> head in Human3.6M's
    training subjects (sampled every 40th/10th frame), so the head points the same way in
    both sources; its length is set later by retargeting.
    """
    eyes = (motion.offsets[motion.index("leftEye")] + motion.offsets[motion.index("rightEye")]) / 2
    return eyes + np.array([0.0, eyes[1], 0.0])


def cmu_joints(motion: BvhMotion, frames: slice | np.ndarray | None = None) -> np.ndarray:
    """The 14 LSP joints of a CMU BVH motion: (F, 14, 3) float64 mm, world z up.

    frames: rows of motion.motion to use (slice or index array), all when None.
    Joints come from ds3d.skeleton.CMU_BVH_TO_LSP; the head top from head_top_offset.
    """
    rotations, positions = global_transforms(motion, frames)
    body = [motion.index(name) for name in CMU_BVH_TO_LSP[:HEAD_TOP]]
    head = motion.index(CMU_BVH_TO_LSP[HEAD_TOP])
    top = positions[:, head] + rotations[:, head] @ head_top_offset(motion)
    joints = np.concatenate([positions[:, body], top[:, None]], axis=1)
    return joints @ _Y_UP_TO_Z_UP.T * CMU_UNIT_MM


def subsample_indices(num_frames: int, frame_time: float, fps: float) -> np.ndarray:
    """Indices (int64) of the frames nearest to the times 0, 1/fps, 2/fps, ..., as long as that
    nearest frame exists. Headers round the frame time (0.03333 for 30 Hz), hence "nearest"."""
    step = 1.0 / (fps * frame_time)  # source frames per output frame
    if step < 1 - 1e-3:
        raise ValueError(f"fps {fps} exceeds the source rate {1 / frame_time:.3f}")
    count = int(np.floor((num_frames - 0.5) / step)) + 1 if num_frames else 0
    return np.minimum(np.round(np.arange(count) * step).astype(np.int64), num_frames - 1)


def bvh_files(source: str | Path | Iterable[str | Path]) -> list[Path]:
    """A folder (its *.bvh and *.bvh.gz, sorted), one file, or an iterable of files."""
    if isinstance(source, str | Path):
        source = Path(source)
        if source.is_dir():
            files = sorted([*source.glob("*.bvh"), *source.glob("*.bvh.gz")])
            if not files:
                raise DataFormatError(f"{source}: no .bvh or .bvh.gz file")
            return files
        return [source]
    return [Path(p) for p in source]


def load_cmu_poses(
    source: str | Path | Iterable[str | Path] | None = None,
    fps: float = 30.0,
    retarget: bool = True,
) -> np.ndarray:
    """CMU BVH clips as (N, 14, 3) float32 poses: mm, Human3.6M world axes (z up), LSP order.

    source: a folder, a file or files; default data_root()/"cmu_bvh".
    fps: output frame rate; each clip is subsampled to the frames nearest to multiples of 1/fps.
    retarget: when True, give every pose the median bone lengths of Human3.6M's training
        subjects (h36m_reference_bone_lengths), keeping bone directions and the pelvis.
    Poses of all files are concatenated in file order.
    """
    files = bvh_files(data_root() / "cmu_bvh" if source is None else source)
    clips = []
    for path in progress(files, desc="BVH files", unit="file"):
        motion = read_bvh(path)
        frames = subsample_indices(motion.num_frames, motion.frame_time, fps)
        clips.append(cmu_joints(motion, frames))
    poses = np.concatenate(clips)
    if retarget:
        poses = retarget_bone_lengths(poses, h36m_reference_bone_lengths())
    return poses.astype(np.float32)


def main() -> None:
    """Print what loading the CMU clips measures: pose count, time, bone lengths."""
    start = time.perf_counter()
    raw = load_cmu_poses(retarget=False)
    raw_s = time.perf_counter() - start
    start = time.perf_counter()
    reference = h36m_reference_bone_lengths()
    ref_s = time.perf_counter() - start
    start = time.perf_counter()
    retargeted = retarget_bone_lengths(raw, reference)
    retarget_s = time.perf_counter() - start
    files = bvh_files(data_root() / "cmu_bvh")
    print(f"{len(files)} files, {raw.shape[0]} poses at 30 fps")
    print(
        f"load (parse + FK + map) {raw_s:.2f} s, H36M reference lengths {ref_s:.2f} s, "
        f"retarget {retarget_s:.3f} s"
    )
    before = np.median(bone_lengths(raw), axis=0)
    after = np.median(bone_lengths(retargeted), axis=0)
    print(f"{'bone':<16}{'CMU mm':>9}{'H36M mm':>9}{'ratio':>7}{'after':>9}")
    for name, b, r, a in zip(BONE_NAMES, before, reference, after, strict=True):
        print(f"{name:<16}{b:9.1f}{r:9.1f}{b / r:7.2f}{a:9.1f}")
    height = raw[:, HEAD_TOP, 2] - raw[:, [R_ANKLE, L_ANKLE], 2].min(axis=1)
    print(f"CMU head-top minus lowest ankle, mm: median {np.median(height):.0f}")


if __name__ == "__main__":
    main()
