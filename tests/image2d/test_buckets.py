"""Padded size buckets (ds3d.image2d.buckets) and what padding to them leaves unchanged."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ds3d.image2d.buckets import STEPS_PER_OCTAVE, bucket
from ds3d.image2d.psm import RootScores
from ds3d.people.search import local_peaks
from ds3d.skeleton import NUM_JOINTS
from tests.image2d.test_psm import STANDING, peaked_unaries, planted_problem


def test_a_bucket_holds_its_size_with_at_most_an_eighth_more():
    sizes = range(1, 5000)
    buckets = [bucket(n) for n in sizes]
    most = 1 + 1 / STEPS_PER_OCTAVE
    assert all(n <= b <= n * most for n, b in zip(sizes, buckets, strict=True))
    assert all(bucket(b) == b for b in buckets)  # a bucket is its own
    assert buckets == sorted(buckets)
    # a bounded set of shapes: eight per octave
    assert len({bucket(n) for n in range(257, 513)}) == STEPS_PER_OCTAVE


def test_the_search_finds_the_same_people_on_maps_padded_with_minus_infinity():
    mixtures = planted_problem(np.random.default_rng(3))
    first = STANDING + np.array([4.0, 2.0])
    peaks = [(j, *first[j], 0.0) for j in range(NUM_JOINTS)]
    peaks += [(j, *(first[j] + [40.0, 0.0]), -1.0) for j in range(NUM_JOINTS)]
    unaries = torch.tensor(peaked_unaries(61, 83, peaks), dtype=torch.float32)[None]
    padded = F.pad(unaries, (0, bucket(83) - 83, 0, bucket(61) - 61), value=-math.inf)
    found = []
    for maps in (unaries, padded):
        upward = RootScores(maps, mixtures)
        roots = local_peaks(upward.root[0], radius=5, count=4)
        found.append((roots, upward.poses(roots[None])))
    (roots, plain), (padded_roots, on_padded) = found
    assert torch.equal(roots, padded_roots)
    assert torch.equal(plain.cells, on_padded.cells)
    torch.testing.assert_close(plain.score, on_padded.score, rtol=0, atol=0)
