import numpy as np

from ds3d.boxes import iou, person_boxes
from ds3d.data.lsp import load_lsp
from ds3d.evaluation.people import match, protocol, score


def test_iou_and_greedy_matching_take_each_person_once():
    truth = np.array([[0, 0, 10, 10], [20, 0, 30, 10]], float)
    predicted = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [40, 40, 50, 50]], float)
    overlap = iou(predicted, truth)
    assert overlap[0, 0] == 1 and overlap[2].max() == 0
    # the surer of two predictions on one person takes it; the other is left over
    assert match(predicted, np.array([0.2, 0.9, 0.5]), truth).tolist() == [1, -1]
    assert match(predicted[:0], np.zeros(0), truth).tolist() == [-1, -1]


def test_person_boxes_widen_the_joints_extent():
    joints = np.zeros((1, 14, 2))
    joints[0, :, 0] = np.linspace(100, 200, 14)
    joints[0, :, 1] = np.linspace(50, 250, 14)
    np.testing.assert_allclose(person_boxes(joints), [[90, 30, 210, 270]])


def test_protocol_is_drawn_from_its_seed_and_keeps_people_apart(data_dir):
    lsp = load_lsp(split="test")
    first, again = protocol(lsp, 12, seed=3), protocol(lsp, 12, seed=3)
    other = protocol(lsp, 12, seed=4)
    assert [c.sources.tolist() for c in first] == [c.sources.tolist() for c in again]
    np.testing.assert_array_equal(first[5].image, again[5].image)
    assert [c.sources.tolist() for c in first] != [c.sources.tolist() for c in other]
    counts = [len(c.joints) for c in first]
    assert min(counts) >= 1 and max(counts) <= 3 and sum(counts) > 12
    for canvas in first:
        assert canvas.image.shape == (480, 640, 3)
        inside = canvas.joints[canvas.located]
        assert (inside >= -1).all() and (inside[:, 0] <= 641).all() and (inside[:, 1] <= 481).all()
        overlap = iou(canvas.boxes(), canvas.boxes())
        np.fill_diagonal(overlap, 0)
        assert (overlap == 0).all()  # nobody pasted over anybody
        # each person's size is the drawn fraction of the canvas height
        extent = np.ptp(canvas.joints, axis=1).max(-1) / 480
        np.testing.assert_allclose(extent, canvas.heights, rtol=0.02)


def test_score_counts_recall_precision_and_pck(data_dir):
    canvases = protocol(load_lsp(split="test"), 6, seed=0)
    perfect = [(c.joints, np.ones(len(c.joints))) for c in canvases]
    report = score(canvases, perfect)
    assert report["all"]["recall"] == 1 and report["all"]["precision"] == 1
    assert report["all"]["pck@0.2"] == 1
    shifted = [(c.joints + 1000, np.ones(len(c.joints))) for c in canvases]
    missed = score(canvases, shifted)
    assert missed["all"]["recall"] == 0 and missed["all"]["precision"] == 0
    assert sum(b["people"] for b in report["bins"].values()) == report["people"]
