"""Growing the forests' trees with scikit-learn and exporting them to the tensor layout that
ds3d.image2d.forest traverses (the layout: that module's docstring)."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import torch
from sklearn.tree import DecisionTreeClassifier

from ds3d.image2d.features import ComparisonPool
from ds3d.image2d.forest import Forest


def float32_threshold(threshold: np.ndarray) -> np.ndarray:
    """The largest float32 t32 <= t, so that for float32 x: x <= t32 iff x <= t (float64).

    scikit-learn compares float32 features with float64 thresholds; rounding the threshold down
    keeps the float32 traversal's branches identical.
    """
    t32 = threshold.astype(np.float32)
    above = t32.astype(np.float64) > threshold
    t32[above] = np.nextafter(t32[above], np.float32(-np.inf))
    return t32


def export_tree(model: DecisionTreeClassifier, pool: ComparisonPool, n_classes: int) -> dict:
    """One fitted scikit-learn tree -> numpy arrays in the export layout (root = node 0).

    The tree's classes must be a subset of range(n_classes); its leaf distributions are spread
    onto all n_classes columns.
    """
    tree = model.tree_
    visited = [0]  # breadth-first, pushing both children of a split together
    new_id = {0: 0}
    queue = deque([0])
    while queue:
        node = queue.popleft()
        if tree.children_left[node] >= 0:
            for child in (tree.children_left[node], tree.children_right[node]):
                new_id[child] = len(visited)
                visited.append(child)
                queue.append(child)
    order = np.asarray(visited)
    n = len(order)
    is_leaf = tree.children_left[order] < 0
    feat = np.where(is_leaf, 0, tree.feature[order])
    if np.abs(np.concatenate([pool.offset1, pool.offset2])).max() > 127 or pool.channel.max() > 255:
        raise ValueError("offsets must fit int8 and channels uint8")
    out: dict[str, Any] = {  # arrays, and the depth
        "channel": np.where(is_leaf, 0, pool.channel[feat]).astype(np.uint8),
        "dy1": np.where(is_leaf, 0, pool.offset1[feat, 0]).astype(np.int8),
        "dx1": np.where(is_leaf, 0, pool.offset1[feat, 1]).astype(np.int8),
        "dy2": np.where(is_leaf, 0, pool.offset2[feat, 0]).astype(np.int8),
        "dx2": np.where(is_leaf, 0, pool.offset2[feat, 1]).astype(np.int8),
        "use2": np.where(is_leaf, 0, pool.use2[feat]).astype(np.uint8),
        "threshold": np.where(
            is_leaf, np.float32(np.inf), float32_threshold(tree.threshold[order])
        ).astype(np.float32),
    }
    left = np.arange(n, dtype=np.int32)
    internal = np.flatnonzero(~is_leaf)
    left[internal] = [new_id[c] for c in tree.children_left[order[internal]]]
    out["left"] = left
    leaf_rows = np.flatnonzero(is_leaf)
    out["leaf"] = np.zeros(n, dtype=np.int32)
    out["leaf"][leaf_rows] = np.arange(len(leaf_rows))
    values = tree.value[order[leaf_rows], 0, :]
    values = values / np.maximum(values.sum(axis=1, keepdims=True), 1e-12)
    dist = np.zeros((len(leaf_rows), n_classes), dtype=np.float32)
    dist[:, model.classes_.astype(np.int64)] = values
    out["leaf_values"] = dist
    out["depth"] = int(tree.max_depth)
    out["source_node"] = order  # scikit-learn's id of each exported node (for checks)
    return out


def stack_trees(trees: list[dict], radius: int, n_channels: int) -> Forest:
    """Concatenate exported trees into one Forest, shifting node and leaf indices."""
    node_off = np.cumsum([0] + [len(t["left"]) for t in trees])
    leaf_off = np.cumsum([0] + [len(t["leaf_values"]) for t in trees])
    cat = {
        k: np.concatenate([t[k] for t in trees])
        for k in ("channel", "dy1", "dx1", "dy2", "dx2", "use2", "threshold")
    }
    left = np.concatenate([t["left"] + o for t, o in zip(trees, node_off[:-1], strict=True)])
    leaf = np.concatenate([t["leaf"] + o for t, o in zip(trees, leaf_off[:-1], strict=True)])
    return Forest(
        **{k: torch.from_numpy(v) for k, v in cat.items()},
        left=torch.from_numpy(left.astype(np.int32)),
        leaf=torch.from_numpy(leaf.astype(np.int32)),
        leaf_values=torch.from_numpy(np.concatenate([t["leaf_values"] for t in trees])).half(),
        roots=torch.from_numpy(node_off[:-1].astype(np.int64)),
        depth=max(t["depth"] for t in trees),
        radius=radius,
        n_channels=n_channels,
    )


def fit_tree(
    features: np.ndarray,
    labels: np.ndarray,
    pool: ComparisonPool,
    n_classes: int,
    seed: int,
    max_depth: int = 20,
    min_samples_leaf: int = 10,
    max_features: int | str = "sqrt",
    splitter: str = "best",
) -> dict:
    """Grow one tree on (n, F) float32 feature values and (n,) int labels; return it exported."""
    model = DecisionTreeClassifier(
        splitter=splitter,
        max_depth=max_depth,
        min_samples_leaf=min_samples_leaf,
        max_features=max_features,
        random_state=seed,
    )
    model.fit(features, labels)
    return export_tree(model, pool, n_classes)
