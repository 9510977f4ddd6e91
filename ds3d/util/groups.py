"""Rows of a batch grouped by a key (a padded shape, a size bucket, which inputs they carry), so
that each group runs as one batched call."""

from __future__ import annotations

from collections.abc import Hashable, Iterable
from typing import TypeVar

K = TypeVar("K", bound=Hashable)


def group_rows(keys: Iterable[K]) -> dict[K, list[int]]:
    """{key: the rows (ascending) whose key it is}, keys in the order first met."""
    groups: dict[K, list[int]] = {}
    for row, key in enumerate(keys):
        groups.setdefault(key, []).append(row)
    return groups
