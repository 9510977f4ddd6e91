"""Random forests on pixel-comparison features: grown with scikit-learn (ds3d.training.trees),
run in torch.

Each tree is grown by scikit-learn on a matrix of pixel-comparison feature values (one column per
feature of a ComparisonPool), then exported to flat tensors. Inference is a tensorised traversal:
every pixel of every image walks every tree at once, one step (a handful of gathers) per depth
level, with no Python loop over pixels or nodes.

Export layout (all trees concatenated, N nodes, L leaves; compact dtypes keep the model small):
    channel:   (N,) uint8    the node's comparison channel (leaves: 0)
    dy1, dx1, dy2, dx2: (N,) int8  its offsets in pixels (leaves: 0)
    use2:      (N,) uint8    0 or 1
    threshold: (N,) float32  go left iff value <= threshold; leaves +inf, so they stay put
    left:      (N,) int32    left child; the right child is always left + 1; leaves point to
                             themselves (renumbered breadth-first so siblings are adjacent)
    leaf:      (N,) int32    row in leaf_values for leaves (unused for internal nodes)
    leaf_values: (L, K) float16  class distribution of each leaf
    roots:     (T,) int64
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from functools import cached_property

import torch

from ds3d.image2d.features import read_offsets, second_reads


@dataclass
class Forest:
    """A forest exported to tensors; see the module docstring for the layout."""

    channel: torch.Tensor
    dy1: torch.Tensor
    dx1: torch.Tensor
    dy2: torch.Tensor
    dx2: torch.Tensor
    use2: torch.Tensor
    threshold: torch.Tensor
    left: torch.Tensor
    leaf: torch.Tensor
    leaf_values: torch.Tensor
    roots: torch.Tensor
    depth: int
    radius: int
    n_channels: int

    @property
    def n_trees(self) -> int:
        return len(self.roots)

    @cached_property
    def node_table(self) -> torch.Tensor:
        """(N, 8) int32, one row per node: the channel, dy, dx of its first read, then of its
        second (features.second_reads), the left child and the threshold's float32 bits. What
        traverse needs on every call, converted once: redoing it cost ~8 ms per call for a
        16-tree layer, a third of a single image's time."""
        first = (self.channel.int(), self.dy1.int(), self.dx1.int())
        second = second_reads(first[0], self.dy2.int(), self.dx2.int(), self.use2, self.n_channels)
        return torch.stack((*first, *second, self.left.int(), self.threshold.view(torch.int32)), 1)

    def first_trees(self, k: int) -> Forest:
        """The forest of its first k trees (the node and leaf rows of a tree follow those of the
        trees before it, so this is a prefix of every array)."""
        if k >= self.n_trees:
            return self
        n_nodes = int(self.roots[k])
        n_leaves = int(self.leaf[:n_nodes].max()) + 1
        return replace(
            self,
            **{f: getattr(self, f)[:n_nodes] for f in _NODE_FIELDS},
            leaf_values=self.leaf_values[:n_leaves],
            roots=self.roots[:k],
        )

    def to(self, device: torch.device | str) -> Forest:
        """The forest with its tensors on `device`."""
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in _TENSORS})

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> Forest:
        return cls(**{f.name: d[f.name] for f in fields(cls)})


_TENSORS = [f for f in fields(Forest) if f.type == "torch.Tensor"]
_NODE_FIELDS = ("channel", "dy1", "dx1", "dy2", "dx2", "use2", "threshold", "left", "leaf")


def traverse(forest: Forest, padded: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Leaf node reached by every pixel in every tree.

    padded: (B, C + 1, H + 2r, W + 2r) float32 from features.pad_channels(channels,
    forest.radius); positions: (P, 2) int64 (y, x) pixels in the UNPADDED image, the same for
    the whole batch, or (B, P, 2), one set per image; every position must lie within
    [0, H) x [0, W) -> (B, T, P) int64 node ids (leaves).

    One step per depth level for all B x T x P walkers: one gather of the node rows, two gathers
    of channel values, a compare. int32 indices halve the memory traffic of the gathers.
    """
    b, c1, hp, wp = padded.shape
    if b * c1 * hp * wp >= 2**31:
        raise ValueError("batch too large for int32 indexing; split it")
    if c1 != forest.n_channels + 1:
        raise ValueError(f"{c1 - 1} channels for a forest on {forest.n_channels}")
    r = forest.radius
    flat = padded.reshape(-1)
    pix = (positions[..., 0] + r) * wp + positions[..., 1] + r  # (P,) or (B, P)
    n_pix = pix.shape[-1]
    start = (torch.arange(b, device=padded.device) * (c1 * hp * wp)).view(b, 1, 1) + pix.view(
        -1, 1, n_pix
    )
    start = start.expand(b, forest.n_trees, -1).reshape(-1).int()
    node = forest.roots.view(1, -1, 1).expand(b, -1, n_pix).reshape(-1).int()
    table = forest.node_table

    def flat_offsets(rows: torch.Tensor) -> torch.Tensor:
        """(M, 6) two reads' (channel, dy, dx) -> (M, 2) their flat offsets from the pixel."""
        reads = rows.view(-1, 2, 3)
        return read_offsets(reads[..., 0], reads[..., 1], reads[..., 2], (c1, hp, wp))

    # The reads' offsets depend on the image's size. With fewer reads to make than the forest
    # has nodes (one small image: about 6,000 walkers), each step converts its walkers' own
    # rows; otherwise one table of offsets for every node, made per call, is cheaper.
    each_step = len(start) * forest.depth < len(table)
    if not each_step:
        table = torch.cat((flat_offsets(table[:, :6]), table[:, 6:]), 1)
    for _ in range(forest.depth):
        row = table.index_select(0, node)
        reads = flat_offsets(row[:, :6]) if each_step else row[:, :2]
        v = flat.index_select(0, start + reads[:, 0]) - flat.index_select(0, start + reads[:, 1])
        node = row[:, -2] + (v > row[:, -1].view(torch.float32))
    return node.view(b, forest.n_trees, -1).long()


def predict_proba(forest: Forest, padded: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Mean leaf class distribution over trees. Same inputs as traverse -> (B, P, K) float32."""
    nodes = traverse(forest, padded, positions)  # (B, T, P)
    # index_select with the int32 rows and the float16 leaves as stored: 3-4x faster than
    # advanced indexing with a converted int64 copy of `leaf`.
    rows = forest.leaf.index_select(0, nodes.view(-1))
    return forest.leaf_values.index_select(0, rows).view(*nodes.shape, -1).float().mean(dim=1)
