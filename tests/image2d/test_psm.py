"""The PSM: exact max-convolution, MAP inference over the tree, and the mixture fit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ds3d.errors import InvalidPose
from ds3d.image2d.maxconv import best_child, max_convolve
from ds3d.image2d.psm import (
    PairwiseMixtures,
    fit_pairwise_mixtures,
    infer,
    local_centroid,
)
from ds3d.skeleton import LIMBS, NUM_JOINTS, PARENT

# A standing person, pixels (x, y), LSP order; the PSM tests plant it on the grid.
STANDING = np.array(
    [
        [22, 58], [22, 46], [23, 34], [31, 34], [32, 46], [32, 58],
        [12, 36], [14, 26], [20, 16], [34, 16], [40, 26], [42, 36],
        [27, 14], [27, 4],
    ],
    dtype=np.float64,
)  # fmt: skip


def brute_message(scores, mean, var, log_weight):
    """numpy double loop: value and argmax (child cell) of the message at every parent cell."""
    height, width = scores.shape
    value = np.full((height, width), -np.inf)
    arg = np.zeros((height, width, 2), dtype=np.int64)
    for yj in range(height):
        for xj in range(width):
            for c in range(len(log_weight)):
                for yi in range(height):
                    for xi in range(width):
                        dx = xi - xj - mean[c, 0]
                        dy = yi - yj - mean[c, 1]
                        v = scores[yi, xi] + log_weight[c]
                        v -= 0.5 * (dx * dx / var[c, 0] + dy * dy / var[c, 1])
                        if v > value[yj, xj]:
                            value[yj, xj], arg[yj, xj] = v, (xi, yi)
    return value, arg


def random_mixture(rng, n, c, spread=3.0):
    mean = rng.normal(0, spread, (n, c, 2))
    var = rng.uniform(0.2, 6.0, (n, c, 2))
    log_weight = rng.normal(0, 1, (n, c))
    return mean, var, log_weight


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_max_convolve_and_best_child_equal_brute_force(dtype, tol):
    rng = np.random.default_rng(1)
    n, height, width, c = 3, 9, 11, 4
    scores = rng.normal(0, 2, (n, height, width))
    scores[0, 2, 3] = -np.inf  # a cell that can never hold the child
    mean, var, log_weight = random_mixture(rng, n, c)
    # the third map's mixture pushes children far off the grid: the border must still win
    mean[2] = [[15.0, -12.0]] * c
    t = [torch.tensor(a, dtype=dtype) for a in (scores, mean, var, log_weight)]
    got = max_convolve(*t).numpy()
    # chunking down to one component of one map must not change anything
    assert np.array_equal(max_convolve(*t, chunk_elements=1).numpy(), got)
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    for i in range(n):
        value, arg = brute_message(scores[i], mean[i], var[i], log_weight[i])
        np.testing.assert_allclose(got[i], value, rtol=tol, atol=tol)
        parent = torch.tensor(np.stack((xs.ravel(), ys.ravel()), 1))
        cell, best = best_child(
            t[0][i : i + 1].expand(len(parent), -1, -1), parent, t[1][i : i + 1], t[2][i : i + 1],
            t[3][i : i + 1],
        )  # fmt: skip
        np.testing.assert_array_equal(cell.numpy(), arg.reshape(-1, 2))
        np.testing.assert_allclose(best.numpy(), value.ravel(), rtol=tol, atol=tol)


def test_max_convolve_shared_mixture_equals_per_map():
    rng = np.random.default_rng(2)
    scores = torch.tensor(rng.normal(0, 1, (5, 7, 8)))
    mean, var, log_weight = (torch.tensor(a) for a in random_mixture(rng, 1, 3))
    shared = max_convolve(scores, mean, var, log_weight)
    per_map = max_convolve(
        scores, mean.expand(5, -1, -1), var.expand(5, -1, -1), log_weight.expand(5, -1)
    )
    torch.testing.assert_close(shared, per_map, rtol=0, atol=0)


def planted_problem(rng, n_poses=400, jitter=1.5):
    """Mixtures (C = 3) fit on jittered copies of STANDING."""
    poses = STANDING[None] + rng.normal(0, jitter, (n_poses, NUM_JOINTS, 2))
    mixtures = fit_pairwise_mixtures(torch.tensor(poses)[None], n_components=3, min_var=1.0)
    return mixtures


def peaked_unaries(height, width, peaks, background=-6.0, sigma=1.0):
    """(14, H, W) log-scores: a Gaussian bump of height 0 at each listed cell (joint, x, y,
    amplitude), on a constant background."""
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    u = np.full((NUM_JOINTS, height, width), background)
    for joint, x, y, amp in peaks:
        bump = amp - 0.5 * ((xs - x) ** 2 + (ys - y) ** 2) / sigma**2
        u[joint] = np.maximum(u[joint], bump)
    return u


def test_infer_recovers_planted_pose_and_rejects_distractors():
    rng = np.random.default_rng(3)
    mixtures = planted_problem(rng)
    height, width, stride = 34, 30, 2.0
    shift = np.array([6.0, 2.0])  # pixels; the pose sits anywhere on the grid
    truth = STANDING + shift
    cells = truth / stride
    peaks = [(j, *cells[j], -1.0) for j in range(NUM_JOINTS)]
    # distractors score higher than the true peaks but sit where no limb can reach them together
    distractors = {6: (3.0, 4.0), 11: (27.0, 30.0), 0: (25.0, 3.0), 13: (5.0, 30.0)}
    peaks += [(j, x, y, 0.0) for j, (x, y) in distractors.items()]
    unaries = torch.tensor(peaked_unaries(height, width, peaks), dtype=torch.float32)[None]
    # without binaries the distractors win: the test relies on the PSM's structure
    assert all(
        tuple(np.unravel_index(int(unaries[0, j].argmax()), (height, width)))[::-1] == xy
        for j, xy in distractors.items()
    )
    result = infer(unaries, mixtures, stride=stride)
    np.testing.assert_allclose(result.joints_2d[0].numpy(), truth, atol=stride)
    assert result.joints_2d.dtype == torch.float32 and result.cells.dtype == torch.long
    np.testing.assert_allclose(result.joints_2d.numpy(), result.cells.numpy() * stride)


def test_local_centroid_finds_sub_cell_peaks_within_its_disc_only():
    # Joint j's map: a Gaussian bump centred up to half a cell off its MAP cell (4, 5).
    cell = torch.tensor([4.0, 5.0])
    centres = cell + torch.tensor([[0.04 * j, -0.02 * j] for j in range(NUM_JOINTS)])
    peaks = [(j, float(x), float(y), 0.0) for j, (x, y) in enumerate(centres)]
    unaries = torch.tensor(peaked_unaries(12, 10, peaks, sigma=1.0), dtype=torch.float32)[None]
    cells = cell.long().expand(1, NUM_JOINTS, 2)
    found = local_centroid(unaries, cells, radius=2, sharpness=1.0)
    assert found.shape == (1, NUM_JOINTS, 2) and found.dtype == torch.float32
    # much nearer the true centre than the cell is (exact at offset 0: the disc is symmetric)
    error, offset = (found[0] - centres).norm(dim=-1), (cell - centres).norm(dim=-1)
    assert float(error[0]) < 1e-5 and bool((error[1:] < 0.2 * offset[1:]).all()), error
    # A higher cell pulls the joint when it lies within the disc (2 cells), not beyond it (3).
    spikes = torch.full((1, NUM_JOINTS, 12, 10), -6.0)
    spikes[0, :, 5, 4] = 0.0
    spikes[0, :7, 5, 6] = 3.0
    spikes[0, 7:, 5, 7] = 3.0
    found = local_centroid(spikes, cells, radius=2, sharpness=1.0)[0]
    assert bool((found[:7, 0] > 5.8).all()) and bool(((found[7:] - cell).abs() < 0.05).all())
    # at the corner of a flat grid no weight lies off it: the joint moves into the grid
    flat = torch.zeros(1, NUM_JOINTS, 6, 6)
    corner = torch.tensor([[0, 0], [3, 2]]).repeat(1, NUM_JOINTS // 2, 1)
    moved = local_centroid(flat, corner, radius=2, sharpness=4.0)[0]
    torch.testing.assert_close(moved[1::2], torch.tensor([3.0, 2.0]).expand(7, 2))
    assert bool((moved[0::2] > 0.5).all())


def test_infer_score_is_log_posterior_of_the_map_pose():
    rng = np.random.default_rng(4)
    mixtures = planted_problem(rng)
    unaries = torch.tensor(rng.normal(-3, 1, (2, NUM_JOINTS, 12, 10)))
    result = infer(unaries, mixtures, stride=4.0)
    flat = result.cells[..., 1] * 10 + result.cells[..., 0]
    unary_at_map = unaries.flatten(2).gather(2, flat[..., None])[..., 0]
    torch.testing.assert_close(result.joint_scores, unary_at_map)
    posterior = unary_at_map.sum(1) + mixtures.log_potentials(result.joints_2d.double()).sum(1)
    torch.testing.assert_close(result.score, posterior.to(result.score.dtype))
    # the MAP beats other poses: move one joint at a time to a random cell
    for _ in range(200):
        cells = result.cells.clone()
        j = int(rng.integers(NUM_JOINTS))
        cells[:, j] = torch.tensor(rng.integers(0, (10, 12), size=(2, 2)))
        flat = cells[..., 1] * 10 + cells[..., 0]
        other = unaries.flatten(2).gather(2, flat[..., None])[..., 0].sum(1)
        other = other + mixtures.log_potentials(cells.double() * 4.0).sum(1)
        assert bool((other <= result.score + 1e-9).all())


def test_infer_batch_equals_items_and_per_item_stride():
    rng = np.random.default_rng(5)
    poses = STANDING[None, None] + rng.normal(0, 2, (3, 200, NUM_JOINTS, 2))
    mixtures = fit_pairwise_mixtures(torch.tensor(poses), n_components=4)
    unaries = torch.tensor(rng.normal(-3, 1, (3, NUM_JOINTS, 11, 13)), dtype=torch.float32)
    stride = torch.tensor([3.0, 4.0, 5.0])
    batch = infer(unaries, mixtures, stride=stride)
    for i in range(3):
        item_mix = PairwiseMixtures(
            mixtures.mean[i : i + 1], mixtures.var[i : i + 1], mixtures.log_gamma[i : i + 1]
        )
        one = infer(unaries[i : i + 1], item_mix, stride=float(stride[i]))
        torch.testing.assert_close(batch.joints_2d[i : i + 1], one.joints_2d)
        torch.testing.assert_close(batch.score[i : i + 1], one.score)
        torch.testing.assert_close(batch.joint_scores[i : i + 1], one.joint_scores)


def sample_mixture(rng, means, stds, freqs, n):
    comp = rng.choice(len(freqs), size=n, p=freqs)
    return means[comp] + rng.normal(0, 1, (n, 2)) * stds[comp], comp


def poses_with_limb_offsets(offsets):
    """(N, 14, 2) poses whose every limb has the given (N, 2) offset child - parent."""
    n = len(offsets)
    joints = np.zeros((n, NUM_JOINTS, 2))
    for i in _top_down():
        joints[:, i] = joints[:, PARENT[i]] + offsets
    return joints


def _top_down():
    order, frontier = [], [PARENT.index(-1)]
    while frontier:
        frontier = [i for p in frontier for i, q in enumerate(PARENT) if q == p]
        order += frontier
    return order


def test_fit_recovers_known_mixture():
    rng = np.random.default_rng(6)
    means = np.array([[30.0, 0.0], [-10.0, 25.0], [0.0, -40.0]])
    stds = np.array([[2.0, 3.0], [1.5, 1.0], [3.0, 2.0]])
    freqs = np.array([0.5, 0.3, 0.2])
    offsets, _ = sample_mixture(rng, means, stds, freqs, 3000)
    joints = torch.tensor(poses_with_limb_offsets(offsets))[None]
    mix = fit_pairwise_mixtures(joints, n_components=3, min_var=1e-6)
    for limb in range(len(LIMBS)):
        order = np.argsort(-mix.log_gamma[0, limb].numpy())  # most frequent first
        np.testing.assert_allclose(mix.mean[0, limb, order].numpy(), means, atol=0.3)
        np.testing.assert_allclose(np.sqrt(mix.var[0, limb, order].numpy()), stds, rtol=0.1)
        np.testing.assert_allclose(
            mix.log_gamma[0, limb, order].numpy(), 0.1 * np.log(freqs), atol=0.01
        )


def test_fit_honours_weights_and_visibility():
    rng = np.random.default_rng(7)
    means = np.array([[20.0, 0.0], [-20.0, 0.0]])
    good, _ = sample_mixture(rng, means, np.ones((2, 2)), np.array([0.5, 0.5]), 400)
    junk = rng.uniform(-200, 200, (300, 2))
    joints = torch.tensor(poses_with_limb_offsets(np.concatenate([good, junk])))[None]
    weights = torch.cat([torch.ones(1, 400), torch.zeros(1, 300)], 1).double()
    reference = fit_pairwise_mixtures(joints[:, :400], n_components=2, seed=3)
    weighted = fit_pairwise_mixtures(joints, weights, n_components=2, seed=3)
    # the junk carries no weight and may even be NaN; mixtures equal the fit without it
    joints[:, 400:, :] = torch.nan
    with_nan = fit_pairwise_mixtures(joints, weights, n_components=2, seed=3)
    by_x = lambda m: np.sort(m.mean[0].numpy(), axis=1)  # noqa: E731  (cluster order is free)
    for mix in (weighted, with_nan):
        np.testing.assert_allclose(by_x(mix), by_x(reference), atol=1e-4)
        np.testing.assert_allclose(
            np.sort(mix.var[0].numpy(), 1), np.sort(reference.var[0].numpy(), 1), atol=1e-4
        )
    # invisible joints: their limbs ignore the junk rows, other limbs still see every row
    joints[:, 400:, :] = torch.tensor(poses_with_limb_offsets(junk))
    visible = torch.ones(1, 700, NUM_JOINTS, dtype=torch.bool)
    visible[:, 400:, 0] = False  # right ankle: only the limb (0, 1) loses the junk rows
    mix = fit_pairwise_mixtures(joints, visible=visible, n_components=2, seed=3)
    limb = [i for i, _ in LIMBS].index(0)
    np.testing.assert_allclose(np.sort(mix.mean[0, limb, :, 0].numpy()), [-20, 20], atol=0.5)
    assert float(mix.var[0, limb].max()) < 3.0
    assert float(mix.var[0, limb + 1].max()) > 100.0  # (1, 2) still sees the junk


def test_fit_rejects_bad_input():
    joints = torch.zeros(1, 10, NUM_JOINTS, 2)
    with pytest.raises(ValueError):
        fit_pairwise_mixtures(joints, torch.zeros(1, 10))
    with pytest.raises(ValueError):
        fit_pairwise_mixtures(joints, -torch.ones(1, 10))
    joints[0, 3, 5] = torch.nan
    with pytest.raises(InvalidPose):
        fit_pairwise_mixtures(joints)
    with pytest.raises(InvalidPose):
        fit_pairwise_mixtures(torch.zeros(10, NUM_JOINTS, 2))
    with pytest.raises(ValueError):
        fit_pairwise_mixtures(torch.zeros(1, 10, NUM_JOINTS, 2), min_var=0.0)


def test_fit_is_deterministic_and_batch_equals_items():
    rng = np.random.default_rng(8)
    joints = torch.tensor(STANDING[None, None] + rng.normal(0, 6, (3, 150, NUM_JOINTS, 2)))
    weights = torch.tensor(rng.uniform(0, 1, (3, 150)))
    a = fit_pairwise_mixtures(joints, weights, n_components=5, seed=11)
    b = fit_pairwise_mixtures(joints, weights, n_components=5, seed=11)
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key])
    # clusters from another seed differ somewhere (the seed is used)
    c = fit_pairwise_mixtures(joints, weights, n_components=5, seed=12)
    assert not torch.equal(a.mean, c.mean)
    # an item's mixture does not depend on the batch it is fitted in
    for i in range(3):
        alone = fit_pairwise_mixtures(
            joints[i : i + 1], weights[i : i + 1], n_components=5, seed=11
        )
        for key, value in alone.state_dict().items():
            torch.testing.assert_close(value[0], a.state_dict()[key][i], rtol=1e-6, atol=1e-5)


def test_mixtures_state_dict_round_trip_and_device():
    rng = np.random.default_rng(9)
    joints = torch.tensor(STANDING[None, None] + rng.normal(0, 3, (1, 50, NUM_JOINTS, 2)))
    mix = fit_pairwise_mixtures(joints, n_components=2)
    state = {k: v.clone() for k, v in mix.state_dict().items()}
    back = PairwiseMixtures.from_state_dict(state).to("cpu")
    assert back.n_components == 2 and back.batch_size == 1
    for key in ("mean", "var", "log_gamma"):
        assert torch.equal(getattr(back, key), getattr(mix, key))
    with pytest.raises(ValueError):
        PairwiseMixtures(mix.mean, -mix.var, mix.log_gamma)
