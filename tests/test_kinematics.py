"""Joint angles (ds3d.kinematics) and their BVH files (ds3d.data.bvh.format_bvh): inverse then
forward kinematics gives the joints back, and two readers, ours and an independent one, place
the written file's joints where they were."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ds3d import kinematics as K
from ds3d.data.bvh import format_bvh, forward_kinematics, parse_bvh
from ds3d.evaluation.h36m import protocol_cases
from ds3d.fit.camera import rotation_matrix
from tests.needs import import_or_missing


@pytest.fixture(scope="module")
def poses(data_dir) -> torch.Tensor:
    """(F, 14, 3) mm, world axes: Human3.6M S11 poses where they stood, frames of several
    sequences seen by the four cameras (one person: the same bones throughout)."""
    cases = protocol_cases(stride=64)
    placed = cases.joints_3d[::7] + cases.roots[::7, None]
    return K.camera_to_world(torch.from_numpy(placed).double())


def test_least_rotation_takes_each_direction_to_the_other():
    torch.manual_seed(0)
    source = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    target = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    target[0] = -source[0]  # the half turn
    turn = K.least_rotation(source, target)
    torch.testing.assert_close((turn @ source[..., None])[..., 0], target)
    torch.testing.assert_close(
        turn @ turn.transpose(-1, -2), torch.eye(3).double().expand(50, 3, 3)
    )
    torch.testing.assert_close(torch.linalg.det(turn), torch.ones(50).double())


def test_every_pose_comes_back_from_its_own_angles(poses):
    """A rig with each pose's own bone lengths: exact, frame by frame."""
    for pose in poses[:20]:
        motion = K.inverse_kinematics(pose[None])
        torch.testing.assert_close(K.forward_kinematics(motion), pose[None], atol=1e-6, rtol=0)


def test_a_clip_whose_bones_keep_their_lengths_comes_back_exactly(poses):
    """One rig for every frame (its bones the median lengths): frames whose bones have those
    lengths come back exactly; the others keep every bone's direction (Human3.6M's 14 joints,
    derived from its markers, move their bones by a few mm)."""
    rigid = K.forward_kinematics(K.inverse_kinematics(poses))
    torch.testing.assert_close(
        K.forward_kinematics(K.inverse_kinematics(rigid)), rigid, atol=1e-6, rtol=0
    )
    error = (rigid - poses).norm(dim=-1)
    assert 0 < float(error.mean()) < 10, float(error.mean())


def test_angles_are_bvh_zxy_euler_angles():
    torch.manual_seed(1)
    turn = rotation_matrix(torch.randn(20, 3, dtype=torch.float64))
    a, b, c = (torch.deg2rad(v) for v in K.zxy_angles(turn).unbind(-1))
    zero, one = torch.zeros_like(a), torch.ones_like(a)

    def about(axis: int, t: torch.Tensor) -> torch.Tensor:
        return rotation_matrix(
            torch.stack([t * (axis == k) + zero for k in range(3)], -1) * one[..., None]
        )

    torch.testing.assert_close(about(2, a) @ about(0, b) @ about(1, c), turn)


def test_a_written_file_reads_back_with_the_joints_in_place(poses):
    motion = K.inverse_kinematics(poses[:10])
    text = format_bvh(K.to_bvh(motion, frame_time=0.04))
    read = parse_bvh(text)
    assert read.num_frames == 10 and read.frame_time == pytest.approx(0.04)
    assert read.channels[0] == K.ROOT_CHANNELS and read.names[0] == "hips"
    columns = [read.index(K.NODES[n].name) for n in K.JOINT_NODES]
    placed = torch.from_numpy(forward_kinematics(read)[:, columns]).double()
    # four decimals in the file, float32 in the reader
    torch.testing.assert_close(placed, K.forward_kinematics(motion), atol=0.05, rtol=0)


def test_an_independent_reader_places_the_joints_alike(poses, tmp_path):
    bvhio = import_or_missing("bvhio", "bvhio is in the dev extra: pip install -e .[dev]")
    motion = K.inverse_kinematics(poses[:3])
    path = tmp_path / "person.bvh"
    path.write_text(format_bvh(K.to_bvh(motion, frame_time=0.04)))
    hierarchy = bvhio.readAsHierarchy(str(path))
    expected = K.forward_kinematics(motion).numpy()
    for frame in range(3):
        hierarchy.loadPose(frame)
        where = {joint.Name: np.array(joint.PositionWorld) for joint, _, _ in hierarchy.layout()}
        placed = np.stack([where[K.NODES[n].name] for n in K.JOINT_NODES])
        np.testing.assert_allclose(placed, expected[frame], atol=0.05)
