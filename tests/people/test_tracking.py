"""People followed through a video (ds3d.people.tracking): the One-Euro filter, and ids that follow
each person from frame to frame and start afresh after a cut."""

from __future__ import annotations

import numpy as np
import torch

from ds3d import kinematics as K
from ds3d.data.h36m import load_cameras, load_h36m_sequences
from ds3d.people.tracking import OneEuro, Tracker, follow, jitter
from ds3d.result import Person
from ds3d.skeleton import NUM_JOINTS


def person(x: float, y: float, depth: float = 4000.0, rng=None) -> Person:
    """A person whose 2D joints fill a 100 x 200 px box at (x, y), standing `depth` mm away."""
    joints_2d = np.stack(
        [np.linspace(x, x + 100, NUM_JOINTS), np.linspace(y, y + 200, NUM_JOINTS)], 1
    ).astype(np.float32)
    joints_3d = np.zeros((NUM_JOINTS, 3), np.float32)
    joints_3d[:, 1] = np.linspace(-900, 900, NUM_JOINTS)
    joints_3d -= (joints_3d[2] + joints_3d[3]) / 2  # hip midpoint at the origin
    noise = 0.0 if rng is None else rng.normal(0, 30, 3)
    return Person(
        box=np.array([x, y, x + 100, y + 200], np.float32),
        score=0.9,
        person_found=True,
        joints_2d=joints_2d,
        joints_2d_initial=joints_2d,
        joints_3d=joints_3d,
        root_position=np.array([x, y, depth], np.float32) + noise,
        focal_px=1000.0,
        focal_assumed=True,
        confidence=np.ones(NUM_JOINTS, np.float32),
        facing_camera=1.0,
        joint_set="all",
        psm_energy=np.zeros(1, np.float32),
    )


def filtered(values: np.ndarray, fps: float, one_euro: OneEuro) -> np.ndarray:
    return np.stack([one_euro(v, 1.0 / fps) for v in values])


def test_one_euro_keeps_a_still_signal_and_calms_its_noise():
    rng = np.random.default_rng(0)
    still = np.full((200, 3), 500.0)
    np.testing.assert_allclose(filtered(still, 50.0, OneEuro()), still)
    noisy = still[:, None] + rng.normal(0, 20, (200, 1, 3))
    assert jitter(filtered(noisy, 50.0, OneEuro())) < jitter(noisy) / 3
    # a step is followed within a bounded lag: most of it after a quarter of a second
    step = np.concatenate([np.zeros((50, 1)), np.full((50, 1), 100.0)])
    followed = filtered(step, 50.0, OneEuro(min_cutoff=2.0, beta=0.0))
    assert followed[49, 0] == 0 and followed[62, 0] > 90


def test_people_keep_their_ids_and_a_cut_starts_new_ones():
    tracker = Tracker(smooth=False)
    first = tracker.update([person(100, 50), person(400, 60)], dt=0.04)
    assert [p.track_id for p in first] == [0, 1]
    # a little later, listed the other way round: each keeps its own
    second = tracker.update([person(404, 62), person(103, 51)], dt=0.04)
    assert [p.track_id for p in second] == [1, 0]
    # a cut: people elsewhere are new ones
    third = tracker.update([person(250, 300), person(10, 280)], dt=0.04)
    assert sorted(p.track_id for p in third) == [2, 3]
    # the people before the cut, gone for longer than max_missed frames, are forgotten
    for _ in range(tracker.max_missed + 1):
        tracker.update([], dt=0.04)
    assert tracker.tracks == []


def test_a_track_is_smoothed_in_camera_coordinates():
    rng = np.random.default_rng(1)
    tracker = Tracker(smooth=True)
    raw, smoothed = [], []
    for _ in range(100):
        seen = person(100, 50, rng=rng)
        (followed,) = tracker.update([seen], dt=0.02)
        raw.append(seen.joints_3d_camera)
        smoothed.append(followed.joints_3d_camera)
        assert followed.track_id == 0
        # hip-centred joints and root still add up to the joints in camera coordinates
        np.testing.assert_allclose(
            (followed.joints_3d[2] + followed.joints_3d[3]) / 2, np.zeros(3), atol=1e-3
        )
    assert jitter(np.stack(smoothed)) < jitter(np.stack(raw)) / 3


def test_a_followed_track_keeps_one_skeleton_that_a_bvh_rig_reproduces(lifter, data_dir):
    """A lifted Human3.6M sequence (S11, camera 1, ground-truth 2D, 200 frames at 12.5 Hz):
    answered frame by frame, its bones change length, and one BVH rig (the bones' median
    lengths) misses its joints by much more than once followed, when within 5 mm on average."""
    sequence = load_h36m_sequences(("S11",))
    poses = sequence[sorted(sequence)[0]][:800:4]
    camera = load_cameras()[("S11", 1)]
    intrinsics = np.repeat(camera.intrinsics[None], len(poses), 0)
    result = lifter.lift(camera.project(poses), intrinsics=intrinsics)
    placed = (result.joints_3d + result.root_position[:, None]).double().numpy()

    def rig_error(joints: np.ndarray) -> float:
        world = K.camera_to_world(torch.from_numpy(joints))
        return float(
            (K.forward_kinematics(K.inverse_kinematics(world)) - world).norm(dim=-1).mean()
        )

    followed = follow(placed, 12.5)
    assert rig_error(followed) < 5.0 < rig_error(placed)
