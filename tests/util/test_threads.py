"""Whole images of a batch on parallel threads (ds3d.util.threads)."""

from __future__ import annotations

import threading

import torch

from ds3d.util.threads import intra_op_threads, map_on_threads, split_rows


def test_rows_split_into_one_contiguous_part_per_thread():
    with intra_op_threads(2):
        assert [p.tolist() for p in split_rows(5)] == [[0, 1, 2], [3, 4]]
        assert [p.tolist() for p in split_rows(1)] == [[0]]  # no empty part
    with intra_op_threads(1):
        assert [p.tolist() for p in split_rows(5)] == [[0, 1, 2, 3, 4]]


def test_parts_run_on_their_own_threads_of_one_intra_op_thread_in_order():
    seen = []

    def work(rows: torch.Tensor) -> list[int]:
        seen.append((threading.get_ident(), torch.get_num_threads()))
        return rows.tolist()

    with intra_op_threads(2):
        parts = split_rows(4)
        assert map_on_threads(work, parts) == [[0, 1], [2, 3]]
        assert torch.get_num_threads() == 2  # the caller's setting is left alone
    # on worker threads (the pool may reuse one for both parts), one intra-op thread each
    assert all(ident != threading.get_ident() and n == 1 for ident, n in seen) and len(seen) == 2
    seen.clear()
    with intra_op_threads(2):
        assert map_on_threads(work, [torch.arange(3)]) == [[0, 1, 2]]
        assert torch.get_num_threads() == 2
    assert seen == [(threading.get_ident(), 2)]  # one part: the calling thread, its threads
