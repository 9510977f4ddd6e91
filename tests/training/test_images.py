"""The training images' labels (ds3d.training.images)."""

from __future__ import annotations

import numpy as np

from ds3d.training.images import faces_camera, observer_centric


def test_observer_centric_labels_follow_the_image_sides():
    joints = np.zeros((14, 2), dtype=np.float32)
    joints[:, 0] = np.arange(14)  # distinct x per joint
    joints[8, 0], joints[9, 0] = 50, 40  # right shoulder right of the left: faces away
    joints[2, 0], joints[3, 0] = 10, 20  # hips as if facing the camera
    visible = np.arange(14) % 2 == 0
    assert not faces_camera(joints)
    obs, vis = observer_centric(joints, visible)
    arm_r, arm_l = [6, 7, 8], [11, 10, 9]
    np.testing.assert_array_equal(obs[arm_r], joints[arm_l])  # arms swapped
    np.testing.assert_array_equal(vis[arm_l], visible[arm_r])
    np.testing.assert_array_equal(obs[:6], joints[:6])  # legs kept
    assert faces_camera(obs)
    again, _ = observer_centric(obs, vis)
    np.testing.assert_array_equal(again, obs)
