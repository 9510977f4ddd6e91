"""Padded size buckets: the 2D stage pads what it batches (a traversal group's channels, the
search's maps) to one of eight sizes per octave of each side, and the joint network's input to
one of four (jointnet.NET_BUCKET_STEPS).

A service sees images of every size. Were every tensor sized by its image, each new size would
bring new oneDNN primitives and buffers of new sizes, and glibc's malloc keeps the free memory
around them: resident memory climbed with the stream of sizes (docs/service-results.md, memory).
Padded to a bucket, the shapes met are a bounded set whose buffers are reused, at most 1/8 more
pixels per side. What is padded is what lies outside an image anyway (zeros, or cells no joint
may take), so the forests and the PSM compute the same as unpadded; the joint network sees more
of the zeros it was trained to see past an image's edge.
"""

from __future__ import annotations

STEPS_PER_OCTAVE = 8


def bucket(size: int, steps: int = STEPS_PER_OCTAVE) -> int:
    """The bucket of a side of `size` px (or cells): the smallest multiple of the octave's step
    at or above it, the step being 1 / steps of the octave's start (2^k <= size < 2^(k+1));
    sizes up to 2 * steps are their own bucket. Fewer steps: fewer shapes, more padding (at
    most 1 / steps of the size)."""
    step = max((1 << (size.bit_length() - 1)) // steps, 1)
    return -(-size // step) * step
