"""BVH reading and forward kinematics, and the CMU source mapped to the 14-joint skeleton."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ds3d.data.bvh import forward_kinematics, parse_bvh, read_bvh
from ds3d.data.cmu import (
    BONES,
    bone_lengths,
    cmu_joints,
    h36m_reference_bone_lengths,
    load_cmu_poses,
    retarget_bone_lengths,
    subsample_indices,
)
from ds3d.errors import DataFormatError
from ds3d.skeleton import HEAD_TOP, L_ANKLE, L_HIP, NECK, R_ANKLE, R_HIP, hip_midpoint
from ds3d.util.paths import data_root
from tests.needs import missing

CMU = data_root() / "cmu_bvh"
H36M = data_root() / "h36m" / "poses_3d_17j.npz"


def cmu_file(name: str) -> Path:
    path = CMU / name
    if not path.is_file():
        missing(f"CMU BVH data not found at {path}")
    return path


def scipy_forward_kinematics(motion, frame: int) -> np.ndarray:
    """An independent FK for one frame: scipy's intrinsic Euler rotations, joint by joint."""
    values = iter(motion.motion[frame])
    rotations, positions = [], []
    for j, parent in enumerate(motion.parents):
        chans = {ch: next(values) for ch in motion.channels[j]}
        order = "".join(ch[0].upper() for ch in motion.channels[j] if ch.endswith("rotation"))
        angles = [chans[f"{axis}rotation"] for axis in order]
        local = Rotation.from_euler(order, angles, degrees=True) if order else Rotation.identity()
        translation = motion.offsets[j].copy()
        for axis, name in enumerate(("Xposition", "Yposition", "Zposition")):
            translation[axis] = chans.get(name, translation[axis])
        if parent < 0:
            rotations.append(local)
            positions.append(translation)
        else:
            rotations.append(rotations[parent] * local)
            positions.append(positions[parent] + rotations[parent].apply(translation))
    return np.array(positions)


@pytest.mark.parametrize(
    ("name", "frames"), [("standard.bvh.gz", [0, 1, 2]), ("salsa_01.bvh.gz", [0, 777, 2242])]
)
def test_fk_matches_an_independent_scipy_chain(name, frames):
    motion = read_bvh(cmu_file(name))
    assert len(motion.names) == 57 and motion.names[0] == "hip"
    positions = forward_kinematics(motion)
    assert positions.shape == (motion.num_frames, 57, 3) and positions.dtype == np.float32
    for f in frames:
        np.testing.assert_allclose(positions[f], scipy_forward_kinematics(motion, f), atol=1e-3)


def test_bones_keep_their_offset_lengths_in_every_frame():
    motion = read_bvh(cmu_file("martial_04.bvh.gz"))
    positions = forward_kinematics(motion)
    child = np.arange(1, len(motion.names))
    lengths = np.linalg.norm(positions[:, child] - positions[:, motion.parents[child]], axis=-1)
    expected = np.linalg.norm(motion.offsets[child], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(expected, lengths.shape), atol=2e-3)
    # and the motion is not the rest pose repeated: joints do move
    assert np.ptp(positions[:, motion.index("rHand")], axis=0).max() > 50


SYNTHETIC = """HIERARCHY
ROOT root
{{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition {root_order}
  JOINT arm
  {{
    OFFSET 1 2 3
    CHANNELS 3 {arm_order}
    End Site
    {{
      OFFSET 0 5 -2
    }}
  }}
}}
MOTION
Frames: 1
Frame Time: 0.01
10 20 30 {root_angles} {arm_angles}
"""


def _synthetic(root_order: str, arm_order: str, root_angles, arm_angles) -> str:
    order = lambda o: " ".join(f"{a}rotation" for a in o)  # noqa: E731
    return SYNTHETIC.format(
        root_order=order(root_order),
        arm_order=order(arm_order),
        root_angles=" ".join(map(str, root_angles)),
        arm_angles=" ".join(map(str, arm_angles)),
    )


@pytest.mark.parametrize(
    ("root_order", "arm_order"), [("ZXY", "XYZ"), ("XYZ", "ZXY"), ("YZX", "ZYX")]
)
def test_rotation_order_is_the_declared_channel_order(tmp_path, root_order, arm_order):
    root_angles, arm_angles = (30.0, -50.0, 75.0), (-40.0, 65.0, 20.0)
    path = tmp_path / "synthetic.bvh"
    path.write_text(_synthetic(root_order, arm_order, root_angles, arm_angles))
    motion = read_bvh(path)
    assert motion.names == ("root", "arm", "arm/End")
    positions = forward_kinematics(motion)[0]
    r_root = Rotation.from_euler(root_order, root_angles, degrees=True)  # intrinsic
    r_arm = Rotation.from_euler(arm_order, arm_angles, degrees=True)
    arm = np.array([10, 20, 30]) + r_root.apply([1, 2, 3])
    end = arm + (r_root * r_arm).apply([0, 5, -2])
    np.testing.assert_allclose(positions, [[10, 20, 30], arm, end], atol=1e-4)
    # the same angles read in the reversed order put the arm elsewhere: the order is honoured
    reversed_text = _synthetic(root_order[::-1], arm_order[::-1], root_angles[::-1], arm_angles)
    other = forward_kinematics(parse_bvh(reversed_text))[0]
    assert np.linalg.norm(other[1] - arm) > 0.5


def test_gzip_and_plain_files_read_the_same(tmp_path):
    source = cmu_file("martial_04.bvh.gz")
    plain = tmp_path / "martial_04.bvh"
    plain.write_bytes(gzip.decompress(source.read_bytes()))
    a, b = read_bvh(source), read_bvh(plain)
    assert a.names == b.names and a.channels == b.channels and a.frame_time == b.frame_time
    np.testing.assert_array_equal(a.parents, b.parents)
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_array_equal(a.motion, b.motion)
    assert a.motion.shape == (1317, 132)


GOOD = (
    _synthetic("ZXY", "XYZ", (1, 2, 3), (4, 5, 6)).replace("Frames: 1", "Frames: 2")
    + "1 2 3 4 5 6 7 8 9\n"
)
# line numbers in GOOD: 5 root CHANNELS, 8 arm OFFSET, 16 MOTION, 18 Frame Time, 20 last frame


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (GOOD.replace("HIERARCHY\n", ""), "line 1: missing HIERARCHY"),
        (GOOD.replace("MOTION", "MOTON"), "no MOTION section"),
        (GOOD.replace("JOINT arm", "JOINT root"), "line 6: joint name 'root' used twice"),
        (
            GOOD.replace("Zrotation Xrotation Yrotation", "Zrotation Wrotation Yrotation"),
            "line 5: unknown channel 'Wrotation'",
        ),
        (GOOD.replace("OFFSET 1 2 3", "OFFSET 1 two 3"), "line 8: bad number 'two'"),
        (GOOD.replace("7 8 9\n", "7 8\n"), "line 20: 8 values, the hierarchy declares 9"),
        (GOOD.replace("7 8 9\n", "7 8 1.2.3\n"), "line 20: bad number '1.2.3'"),
        (GOOD.replace("7 8 9\n", "7 8 nan\n"), "line 20: bad number 'nan'"),
        (GOOD.replace("Frames: 2", "Frames: 3"), "declares 3 frames, found 2"),
        (GOOD.replace("Frame Time: 0.01", "Frame Tim: 0.01"), "line 18: expected 'Frame Time:'"),
        (GOOD.replace("    }\n  }\n}", "    }\n  }\n"), "line 14: hierarchy ends early"),
    ],
)
def test_malformed_files_raise_data_format_error_with_the_line(tmp_path, text, message):
    parse_bvh(GOOD)  # the unbroken text is fine
    path = tmp_path / "broken.bvh"
    path.write_text(text)
    with pytest.raises(DataFormatError, match=message.replace("(", r"\(")) as info:
        read_bvh(path)
    assert str(path) in str(info.value)


def test_truncated_and_missing_gzip_raise_data_format_error(tmp_path):
    path = tmp_path / "cut.bvh.gz"
    path.write_bytes(gzip.compress(GOOD.encode())[:-20])
    with pytest.raises(DataFormatError, match="truncated"):
        read_bvh(path)
    with pytest.raises(DataFormatError, match="no such file"):
        read_bvh(tmp_path / "absent.bvh")


def test_subsample_indices_pick_the_nearest_frames():
    np.testing.assert_array_equal(subsample_indices(10, 1 / 120, 30), [0, 4, 8])
    np.testing.assert_array_equal(subsample_indices(11, 1 / 120, 25), [0, 5, 10])  # 0, 4.8, 9.6
    np.testing.assert_array_equal(subsample_indices(10, 1 / 120, 25), [0, 5])  # 9.6 is past 9
    np.testing.assert_array_equal(subsample_indices(3, 0.03333, 30), [0, 1, 2])  # rounded header
    assert len(subsample_indices(0, 1 / 120, 30)) == 0
    with pytest.raises(ValueError, match="exceeds"):
        subsample_indices(10, 1 / 30, 60)


def test_cmu_poses_are_millimetres_z_up_and_right_handed():
    standard, salsa = cmu_file("standard.bvh.gz"), cmu_file("salsa_01.bvh.gz")
    poses = load_cmu_poses([standard, salsa], fps=30, retarget=False)
    assert poses.shape == (3 + 561, 14, 3) and poses.dtype == np.float32  # salsa: 2243 frames/4
    assert np.isfinite(poses).all()
    # the subsample is frames 0, 4, 8, ... of the clip
    motion = read_bvh(salsa)
    np.testing.assert_allclose(poses[3:6], cmu_joints(motion, [0, 4, 8]), atol=1e-3)
    ankles_z = poses[:, [R_ANKLE, L_ANKLE], 2]
    height = poses[:, HEAD_TOP, 2] - ankles_z.min(axis=1)
    assert 1400 < height[0] < 2000  # the rest pose stands upright
    assert 1400 < np.percentile(height, 90) < 2000  # a standing dancer, in mm, z up
    assert (poses[:, HEAD_TOP, 2] > ankles_z.max(axis=1)).all()
    # handedness: with x = right, y = forward, z = up, (right x up) points backwards, and the
    # head top leans forward of the neck; a mirrored axis map would flip the sign
    right = poses[:, R_HIP] - poses[:, L_HIP]
    up = poses[:, NECK] - hip_midpoint(poses)
    lean = poses[:, HEAD_TOP] - poses[:, NECK]
    assert np.mean(np.einsum("ni,ni->n", np.cross(right, up), lean) < 0) > 0.9


def _directions(poses: np.ndarray) -> np.ndarray:
    vectors = [poses[:, j] - (hip_midpoint(poses) if p < 0 else poses[:, p]) for j, p in BONES]
    vectors = np.stack(vectors, axis=1)
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def test_retargeting_sets_lengths_and_keeps_directions_and_pelvis():
    rng = np.random.default_rng(0)
    poses = rng.normal(scale=300.0, size=(50, 14, 3))
    lengths = rng.uniform(50.0, 500.0, size=13)
    out = retarget_bone_lengths(poses, lengths)
    np.testing.assert_allclose(bone_lengths(out), np.broadcast_to(lengths, (50, 13)), rtol=1e-9)
    np.testing.assert_allclose(_directions(out), _directions(poses), atol=1e-9)
    np.testing.assert_allclose(hip_midpoint(out), hip_midpoint(poses), atol=1e-9)
    with pytest.raises(ValueError, match="shape"):
        retarget_bone_lengths(poses, lengths[:12])


def test_retargeted_cmu_poses_take_human36m_training_proportions():
    if not H36M.is_file():
        missing(f"Human3.6M poses not found at {H36M}")
    reference = h36m_reference_bone_lengths()
    assert ((reference > 100) & (reference < 600)).all()  # mm
    # left and right bones of the (symmetric) Human3.6M skeletons agree: the bone table pairs up
    np.testing.assert_allclose(reference[[1, 2, 6, 7, 8]], reference[[3, 4, 9, 10, 11]], atol=2)
    salsa = cmu_file("salsa_01.bvh.gz")
    raw = load_cmu_poses(salsa, retarget=False)
    poses = load_cmu_poses(salsa)
    np.testing.assert_allclose(
        bone_lengths(poses), np.broadcast_to(reference, (561, 13)), atol=0.05
    )
    np.testing.assert_allclose(_directions(poses), _directions(raw), atol=1e-4)


def test_position_channels_replace_the_offset_on_their_axes():
    # the usual reading (MotionBuilder, Blender): a position channel is the local translation
    # on its axis; an axis without a channel keeps the OFFSET
    text = _synthetic("ZXY", "XYZ", (0, 0, 0), (0, 0, 0)).replace("OFFSET 0 0 0", "OFFSET 7 8 9")
    text = text.replace(
        "CHANNELS 6 Xposition Yposition Zposition", "CHANNELS 5 Xposition Zposition"
    )
    text = text.replace("10 20 30", "10 30")
    positions = forward_kinematics(parse_bvh(text))[0]
    np.testing.assert_allclose(positions[0], [10, 8, 30])
    np.testing.assert_allclose(positions[1], [11, 10, 33])
