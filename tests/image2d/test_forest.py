"""The tensorised forest traversal against a plain walk of the same scikit-learn trees."""

import numpy as np
import pytest
import torch
from sklearn.tree import DecisionTreeClassifier

from ds3d.image2d import features as ft
from ds3d.image2d.forest import predict_proba, traverse
from ds3d.training.trees import export_tree, float32_threshold, stack_trees

RADIUS = 6


def reference_leaf(tree, pool, channels: np.ndarray, y: int, x: int) -> int:
    """Walk one scikit-learn tree for pixel (y, x) of channels (C, H, W), reading out-of-image
    pixels as 0, comparing float32 values with float64 thresholds as scikit-learn does."""
    _, h, w = channels.shape

    def read(c, yy, xx):
        return channels[c, yy, xx] if 0 <= yy < h and 0 <= xx < w else np.float32(0)

    node = 0
    while tree.children_left[node] >= 0:
        f = tree.feature[node]
        c = pool.channel[f]
        (dy1, dx1), (dy2, dx2) = pool.offset1[f], pool.offset2[f]
        second = read(c, y + dy2, x + dx2) if pool.use2[f] else np.float32(0)
        value = np.float32(read(c, y + dy1, x + dx1) - second)
        go_left = float(value) <= tree.threshold[node]
        node = tree.children_left[node] if go_left else tree.children_right[node]
    return node


def _grow(rng, channels: torch.Tensor, n_trees: int):
    """Trees grown on the features of random pixels with random labels (deep, many ties)."""
    models, pools, exported = [], [], []
    b, c, h, w = channels.shape
    padded = ft.pad_channels(channels, RADIUS)
    for t in range(n_trees):
        pool = ft.sample_pool(rng, 48, RADIUS, n_image_channels=c)
        img = t % b
        pos = torch.from_numpy(np.stack([rng.integers(0, h, 600), rng.integers(0, w, 600)], 1))
        x = ft.evaluate_pool(padded[img], RADIUS, pos, pool).numpy()
        y = rng.integers(0, 5, len(x))
        model = DecisionTreeClassifier(max_depth=14, random_state=t, max_features=8).fit(x, y)
        models.append(model)
        pools.append(pool)
        exported.append(export_tree(model, pool, n_classes=5))
    return models, pools, exported


def test_traversal_matches_reference_walk_exactly():
    rng = np.random.default_rng(0)
    # Quantised values make many pixels fall exactly on thresholds: the hard case.
    channels = torch.from_numpy(rng.integers(0, 7, (2, 3, 17, 23)).astype(np.float32) / 3)
    models, pools, exported = _grow(rng, channels, n_trees=4)
    forest = stack_trees(exported, RADIUS, n_channels=3)
    h, w = channels.shape[2:]
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    positions = torch.stack([yy.reshape(-1), xx.reshape(-1)], 1)
    padded = ft.pad_channels(channels, RADIUS)
    leaves = traverse(forest, padded, positions)  # (B, T, P)
    assert leaves.shape == (2, 4, h * w)
    # A few walkers convert their own reads at each step (many convert one table per call):
    # the same leaves.
    for i in (0, 57, h * w - 1):
        np.testing.assert_array_equal(
            traverse(forest, padded, positions[i : i + 1]), leaves[..., i : i + 1]
        )
    offsets = forest.roots.tolist()
    for b in range(2):
        arr = channels[b].numpy()
        for t, (model, pool, tree) in enumerate(zip(models, pools, exported, strict=True)):
            got = tree["source_node"][leaves[b, t].numpy() - offsets[t]]
            want = [reference_leaf(model.tree_, pool, arr, int(y), int(x)) for y, x in positions]
            np.testing.assert_array_equal(got, want)


def test_traversal_agrees_with_scikit_learn_apply():
    rng = np.random.default_rng(1)
    channels = torch.from_numpy(rng.standard_normal((1, 4, 20, 20)).astype(np.float32))
    models, pools, exported = _grow(rng, channels, n_trees=2)
    forest = stack_trees(exported, RADIUS, n_channels=4)
    positions = torch.from_numpy(np.stack([rng.integers(0, 20, 300), rng.integers(0, 20, 300)], 1))
    padded = ft.pad_channels(channels, RADIUS)
    leaves = traverse(forest, padded, positions)
    for t, (model, pool, tree) in enumerate(zip(models, pools, exported, strict=True)):
        x = ft.evaluate_pool(padded[0], RADIUS, positions, pool).numpy()
        got = tree["source_node"][leaves[0, t].numpy() - forest.roots[t].item()]
        np.testing.assert_array_equal(got, model.apply(x))
    # predict_proba is the mean of the trees' normalised leaf distributions
    proba = predict_proba(forest, padded, positions)[0].numpy()
    want = np.mean(
        [
            np.pad(
                m.predict_proba(ft.evaluate_pool(padded[0], RADIUS, positions, p).numpy()),
                ((0, 0), (0, 5 - len(m.classes_))),
            )
            for m, p in zip(models, pools, strict=True)
        ],
        axis=0,
    )
    np.testing.assert_allclose(proba, want, atol=1e-3)  # float16 leaves


def test_first_trees_is_the_forest_of_those_trees_alone():
    rng = np.random.default_rng(4)
    channels = torch.from_numpy(rng.standard_normal((1, 3, 16, 16)).astype(np.float32))
    exported = _grow(rng, channels, n_trees=3)[2]
    padded = ft.pad_channels(channels, RADIUS)
    positions = torch.from_numpy(np.stack([rng.integers(0, 16, 200), rng.integers(0, 16, 200)], 1))
    head = stack_trees(exported, RADIUS, n_channels=3).first_trees(2)
    alone = stack_trees(exported[:2], RADIUS, n_channels=3)
    assert head.n_trees == 2 and len(head.leaf_values) == len(alone.leaf_values)
    torch.testing.assert_close(
        traverse(head, padded, positions), traverse(alone, padded, positions)
    )
    torch.testing.assert_close(
        predict_proba(head, padded, positions), predict_proba(alone, padded, positions)
    )


def test_float32_threshold_keeps_float64_comparisons():
    rng = np.random.default_rng(2)
    t64 = rng.standard_normal(10000)
    t32 = float32_threshold(t64)
    assert t32.dtype == np.float32
    for x in (t32, np.nextafter(t32, np.float32(np.inf)), np.nextafter(t32, np.float32(-np.inf))):
        np.testing.assert_array_equal(x <= t32, x.astype(np.float64) <= t64)


def test_traverse_rejects_batches_beyond_int32_indexing():
    forest = stack_trees(
        _grow(np.random.default_rng(3), torch.zeros(1, 1, 8, 8), 1)[2], RADIUS, n_channels=1
    )
    big = torch.zeros(1, 1, 30, 30).expand(2**31 // (30 * 30) + 1, -1, -1, -1)  # no memory
    with pytest.raises(ValueError, match="int32"):
        traverse(forest, big, torch.zeros(1, 2, dtype=torch.long))
