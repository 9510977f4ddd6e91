import numpy as np
import pytest
import torch

from ds3d.boxes import person_boxes, suppress
from ds3d.data.lsp import load_lsp
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import RootScores, infer
from ds3d.io.images import read_image
from ds3d.people.search import (
    Proposals,
    SearchParams,
    frames_image,
    level_extents,
    level_people,
    local_peaks,
    propose,
)
from ds3d.skeleton import NUM_JOINTS
from tests.image2d.test_psm import STANDING, peaked_unaries, planted_problem


def test_levels_reach_from_the_smallest_to_the_largest_person():
    params = SearchParams()
    extents = level_extents(480, params)
    assert extents[0] * 0.7 == pytest.approx(params.min_height * 480)
    assert extents[-1] * 1.3 >= params.max_height * 480 > extents[-2] * 1.3
    ratios = np.diff(np.log(extents))
    np.testing.assert_allclose(ratios, np.log(params.level_ratio))


def test_no_level_seeks_people_below_the_pixel_floor():
    params = SearchParams()
    small = level_extents(170, params)  # min_height alone would seek 26 px people
    assert small[0] * 0.7 == pytest.approx(params.min_extent_px)
    assert small[-1] * 1.3 >= params.max_height * 170
    assert len(small) < len(level_extents(480, params))
    assert level_extents(40, params) == []  # nobody in it could be min_extent_px tall


def test_local_peaks_are_the_best_separated_maxima():
    scores = torch.zeros(20, 30)
    scores[5, 5], scores[5, 6], scores[15, 25], scores[2, 20] = 9.0, 8.0, 7.0, 1.0
    cells = local_peaks(scores, radius=2, count=2)
    assert cells.tolist() == [[5, 5], [25, 15]]


def test_two_people_are_two_root_peaks_and_their_own_poses():
    """Unaries with two copies of one pose far apart: the two best root peaks back-track to the
    two poses, and the best root's pose is infer's MAP."""
    mixtures = planted_problem(np.random.default_rng(3))
    height, width = 70, 100
    first = STANDING + np.array([4.0, 2.0])  # px = cells (stride 1)
    peaks = [(j, *first[j], 0.0) for j in range(NUM_JOINTS)]
    peaks += [(j, *(first[j] + [50.0, 0.0]), -1.0) for j in range(NUM_JOINTS)]
    unaries = torch.tensor(peaked_unaries(height, width, peaks), dtype=torch.float32)[None]
    cells = torch.from_numpy(first).round().long()
    upward = RootScores(unaries, mixtures)
    roots = local_peaks(upward.root[0], radius=5, count=2)
    found = upward.poses(roots[None])
    np.testing.assert_allclose(found.cells[0, 0], cells, atol=1)
    np.testing.assert_allclose(found.cells[0, 1], cells + torch.tensor([50, 0]), atol=1)
    assert found.score[0, 0] > found.score[0, 1]
    best = infer(unaries, mixtures)
    np.testing.assert_array_equal(best.cells[0], found.cells[0, 0])
    assert float(best.score[0]) == pytest.approx(float(found.score[0, 0]))


def test_suppression_keeps_the_better_of_overlapping_people():
    pose = np.random.default_rng(0).uniform(0, 100, (NUM_JOINTS, 2))
    poses = np.stack([pose, pose + 3, pose + 500])
    kept = suppress(person_boxes(poses), np.array([0.2, 0.9, 0.5]))
    assert kept.tolist() == [1, 2]


def test_a_levels_people_do_not_depend_on_the_levels_searched_with_it():
    """Levels of other shapes share a PSM padded with -inf (padded_groups): each level answers
    the poses and root scores it answers alone."""
    mixtures = planted_problem(np.random.default_rng(3))
    rng = np.random.default_rng(4)
    levels = []
    for height, width, shift in ((40, 50, 3.0), (28, 36, 1.0), (30, 34, 6.0)):
        peaks = [(j, *(STANDING[j] + shift), 0.0) for j in range(NUM_JOINTS)]
        unaries = peaked_unaries(height, width, peaks) + rng.normal(0, 0.3, (height, width))
        levels.append(torch.tensor(unaries, dtype=torch.float32)[None])
    params = SearchParams()
    together = level_people(levels, mixtures, 8, params)
    for level, (poses, scores) in zip(levels, together, strict=True):
        ((alone_poses, alone_scores),) = level_people([level], mixtures, 8, params)
        np.testing.assert_array_equal(poses, alone_poses)
        np.testing.assert_array_equal(scores, alone_scores)
        assert len(scores) > 0


def test_a_proposal_frames_the_image_when_sure_and_its_crop_holds_the_image():
    params, model = SearchParams(), EstimatorParams()
    image = np.zeros((200, 120, 3), np.uint8)
    ys, xs = np.linspace(15.0, 185.0, NUM_JOINTS), np.linspace(25.0, 95.0, NUM_JOINTS)
    filling = np.stack([xs, ys], 1)[None].astype(np.float32)

    def proposals(poses: np.ndarray, score: float) -> Proposals:
        return Proposals(poses, np.array([score], np.float32), [])

    sure = params.proposal_floor + 1
    assert frames_image(proposals(filling, sure), image, model, params)
    assert not frames_image(proposals(filling, params.proposal_floor - 1), image, model, params)
    assert not frames_image(proposals(0.3 * filling + 40, sure), image, model, params)
    nobody = Proposals(filling[:0], np.zeros(0, np.float32), [])
    assert not frames_image(nobody, image, model, params)


def test_the_best_person_of_a_framed_photo_is_found_without_the_coarsest_level(data_dir):
    """An LSP photo is a tight crop around its person: asked for its best person alone, the
    search leaves its coarsest level out and proposes that person as a search of every level
    does; asked for everyone, and in an image that frames nobody, every level is searched."""
    estimator, params = PoseEstimator2D.load(), SearchParams()
    photo = read_image(load_lsp(split="test").image_paths[0])
    blank = np.full_like(photo, 128)
    levels = len(level_extents(photo.shape[0], params))
    best, every, nobody = propose(
        estimator, [photo, photo, blank], params, best_only=[True, False, True]
    )
    assert levels >= 2 and len(every.levels) == len(nobody.levels) == levels
    assert len(best.levels) == levels - 1
    np.testing.assert_allclose(best.poses[0], every.poses[0])
    assert best.scores[0] == every.scores[0] >= params.proposal_floor


def test_the_search_reports_its_networks_time(data_dir):
    """timings["jointnet"] grows by the joint network's seconds over the levels, added to what
    the dict holds, and only where a level was searched."""
    estimator, params = PoseEstimator2D.load(), SearchParams()
    photo = read_image(load_lsp(split="test").image_paths[0])
    held, fresh, none = {"jointnet": 1.0}, {}, {}
    propose(estimator, [photo], params, best_only=[True], timings=held)
    propose(estimator, [photo, photo], params, timings=fresh)
    propose(estimator, [], params, timings=none)
    assert 1.0 < held["jointnet"] and 0.0 < fresh["jointnet"] and none.get("jointnet", 0.0) == 0
