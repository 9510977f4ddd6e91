"""Rows of a batch grouped by a key (a padded shape, a size bucket, which inputs they carry), so
that each group runs as one batched call."""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Sequence
from typing import TypeVar

K = TypeVar("K", bound=Hashable)


def group_rows(keys: Iterable[K]) -> dict[K, list[int]]:
    """{key: the rows (ascending) whose key it is}, keys in the order first met."""
    groups: dict[K, list[int]] = {}
    for row, key in enumerate(keys):
        groups.setdefault(key, []).append(row)
    return groups


def padded_groups(shapes: Sequence[tuple[int, int]], call_cost: float) -> list[list[int]]:
    """Rows of (h, w) maps grouped to run as one call each, every member padded to its group's
    shape (the largest h and the largest w among them): taken largest first, a row joins the
    first group where the padding it adds (its own, and the others' where it widens the group)
    costs at most call_cost, else it starts one. A map's cost is h * w * max(h, w), the
    candidates of a separable max-convolution (ds3d.image2d.maxconv); call_cost, what one more
    call costs in those units. Returns the groups' rows, each ascending."""
    groups: list[tuple[int, int, list[int]]] = []  # height, width, rows
    for row in sorted(range(len(shapes)), key=lambda r: -_map_cost(*shapes[r])):
        h, w = shapes[row]
        for k, (gh, gw, rows) in enumerate(groups):
            height, width = max(gh, h), max(gw, w)
            grown = (len(rows) + 1) * _map_cost(height, width) - len(rows) * _map_cost(gh, gw)
            if grown - _map_cost(h, w) <= call_cost:
                groups[k] = (height, width, [*rows, row])
                break
        else:
            groups.append((h, w, [row]))
    return [sorted(rows) for _, _, rows in groups]


def _map_cost(height: int, width: int) -> int:
    return height * width * max(height, width)
