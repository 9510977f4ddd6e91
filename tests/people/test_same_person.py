"""When two poses answered in one image are one person found twice (ds3d.people.same_person),
and the suppression that drops the second reading."""

import numpy as np

from ds3d.boxes import iou, person_boxes, suppress
from ds3d.people.same_person import joints_on_bones, shared_joints
from ds3d.skeleton import LIMBS, NUM_JOINTS


def test_a_partial_pose_of_an_answered_person_is_one_person_a_neighbour_is_not():
    rng = np.random.default_rng(0)
    whole = np.stack([rng.uniform(100, 220, NUM_JOINTS), np.linspace(50, 350, NUM_JOINTS)], 1)
    partial = whole.copy()  # its upper joints as the whole pose's, the rest huddled beside them
    partial[5:] = whole[4] + np.array([-60.0, -10.0])
    neighbour = whole + np.array([50.0, 0.0])  # beside it: the boxes overlap, no joint shared
    poses = np.stack([whole, partial, neighbour])
    boxes, scores = person_boxes(poses), np.array([0.9, 0.95, 0.8])
    assert iou(boxes[:1], boxes[1:2])[0, 0] < 0.5 and iou(boxes[:1], boxes[2:])[0, 0] > 0.3
    shared = shared_joints(poses, radius=0.1)
    assert shared[0, 1] == 5 and shared[0, 2] == 0 and shared[1, 0] == 5
    # by box overlap alone every one stays; the partial pose is the surer, so the whole goes
    assert suppress(boxes, scores, 0.5).tolist() == [1, 0, 2]
    assert suppress(boxes, scores, 0.5, shared >= 3).tolist() == [1, 2]


def test_a_pose_drawn_along_another_ones_bones_is_one_person_a_neighbour_is_not():
    """A second reading of one body, its joints along the first's limbs and not at its joints,
    has every joint on the first's bones; a neighbour beside it, its box overlapping, few."""
    rng = np.random.default_rng(0)
    whole = np.stack([rng.uniform(100, 220, NUM_JOINTS), np.linspace(50, 350, NUM_JOINTS)], 1)
    child, parent = (list(side) for side in zip(*LIMBS, strict=True))
    along = (whole[child] + whole[parent]) / 2  # the 13 bones' middles, and a quarter of one
    along = np.concatenate([along, 0.75 * whole[child[:1]] + 0.25 * whole[parent[:1]]])
    neighbour = whole + np.array([50.0, 0.0])
    poses = np.stack([whole, along, neighbour])
    on_bones = joints_on_bones(poses, radius=0.035)
    assert np.diag(on_bones).tolist() == [NUM_JOINTS] * 3  # a pose's joints end its bones
    assert on_bones[1, 0] == NUM_JOINTS
    assert on_bones[2, 0] < 9 and on_bones[0, 2] < 9
    # the reading along the bones is the surer here, and the whole pose goes with it (by this
    # rule alone: the boxes' overlap is not asked)
    boxes, scores = person_boxes(poses), np.array([0.9, 0.95, 0.8])
    same = (on_bones >= 9) | (on_bones >= 9).T
    assert suppress(boxes, scores, 1.0, same).tolist() == [1, 2]
