"""People in photos: a protocol of canvases built from LSP (or LSPet), people pasted at any size.

LSP's images are crops around one person; LSPet's too, its people those with all 14 joints
annotated (an occluded joint left out would shrink the person's true box). A canvas (640 x 480
by default) holds 1 to 3 of them, each scaled so that its person spans a drawn fraction of the
canvas height (15-100 %), pasted at a random place where it covers no other person; the first
pasted image (the largest person), its border replicated, also fills the rest of the canvas, so
the background is image content without people. Everything is drawn from one seed: the same seed
gives the same canvases.

Two harder kinds, each a drawn share of the canvases (`protocol`'s `empty` and `cut`):
- empty: no person at all, the canvas filled from the part of an LSP image beside its person
  (the widest band clear of the person's box), scaled up: cluttered scenes where every answer is
  a phantom;
- cut: each person cut by the canvas's edge (a bottom edge half the time, the legs gone, else
  left, right or top), a drawn 10-40 % of its extent beyond it; PCK scores its joints within
  the canvas.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ds3d.boxes import iou, person_boxes
from ds3d.data.lsp import PoseAnnotations, load_lsp, load_lspet
from ds3d.io.images import read_image

CANVAS = (640, 480)  # width, height px
SIZE_BINS = ((0.15, 0.25), (0.25, 0.5), (0.5, 1.0))  # person height / canvas height
LARGE = 0.25  # people at least this tall (of the canvas height) make the `large` figures
CUT_SIDES = (0.2, 0.2, 0.1, 0.5)  # how often a person is cut at the left, right, top, bottom
CUT_SHARE = (0.1, 0.4)  # of the person's extent beyond the edge
EMPTY_MIN_PX = 24  # the narrowest band beside a person that fills an empty canvas


@dataclass(frozen=True)
class Canvas:
    """One protocol image: image (H, W, 3) uint8 RGB; joints (P, 14, 2) px and located (P, 14)
    bool of the P people on it (a cut person's joints beyond the edge too); sources (P,) their
    LSP indices; heights (P,) their size (the longer side of their joints' extent) as a fraction
    of the canvas height."""

    image: np.ndarray
    joints: np.ndarray
    located: np.ndarray
    sources: np.ndarray
    heights: np.ndarray

    def boxes(self) -> np.ndarray:
        """(P, 4) x0, y0, x1, y1 px: each person's box (person_boxes) within the canvas."""
        return self.within(person_boxes(self.joints, self.located))

    def within(self, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) boxes clipped to the canvas: what of a person cut by its edge can be seen."""
        height, width = self.image.shape[:2]
        return np.clip(boxes, 0, [width, height, width, height])

    def inside(self) -> np.ndarray:
        """(P, 14) bool: the located joints within the canvas, those PCK scores."""
        height, width = self.image.shape[:2]
        within = (self.joints >= 0).all(-1) & (self.joints < np.array([width, height])).all(-1)
        return self.located & within


def compose(
    annotations: PoseAnnotations,
    sources: list[int],
    heights: list[float],
    rng: np.random.Generator,
    size: tuple[int, int] = CANVAS,
    tries: int = 50,
    cuts: list[tuple[int, float] | None] | None = None,
) -> Canvas:
    """One canvas of the people `sources` (LSP indices), each scaled to its fraction of `heights`
    of the canvas height and placed where its pasted image covers no person already there (a
    person that finds no such place in `tries` draws is left out; the first always fits).
    cuts: per person None, or (side, share): the person cut by that edge of the canvas (0 left,
    1 right, 2 top, 3 bottom), that share of its extent beyond it (`_cut`)."""
    width, height = size
    canvas: np.ndarray | None = None
    placed_boxes: list[np.ndarray] = []
    people = []
    for i, (source, fraction) in enumerate(zip(sources, heights, strict=True)):
        image = read_image(annotations.image_paths[source])
        located = annotations.located[source]
        joints = annotations.joints[source]
        extent = np.ptp(joints[located], axis=0).max()  # standing or lying, its longer side
        scale = fraction * height / max(extent, 1.0)
        patch = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        points = joints * scale
        patch, points = _fit_patch(patch, points, located, size)
        cut = None if cuts is None else cuts[i]
        if cut is not None:
            patch, points = _cut(patch, points, located, *cut)
        ph, pw = patch.shape[:2]
        for _ in range(tries):
            x, y = int(rng.integers(0, width - pw + 1)), int(rng.integers(0, height - ph + 1))
            if cut is not None:  # flush with the edge that cuts the person
                x = {0: 0, 1: width - pw}.get(cut[0], x)
                y = {2: 0, 3: height - ph}.get(cut[0], y)
            rect = np.array([[x, y, x + pw, y + ph]], np.float64)
            shifted = points + np.array([x, y])
            person = person_boxes(shifted[None], located[None])
            hidden = placed_boxes and (iou(rect, np.concatenate(placed_boxes)) > 0).any()
            if canvas is None or not hidden:
                break
        else:
            continue
        if canvas is None:  # the first image, its border replicated, is the background
            canvas = cv2.copyMakeBorder(
                patch, y, height - y - ph, x, width - x - pw, cv2.BORDER_REPLICATE
            )
        canvas[y : y + ph, x : x + pw] = patch
        placed_boxes.append(person)
        people.append((shifted, located, source, fraction))
    joints, located, sources_kept, fractions = zip(*people, strict=True)
    assert canvas is not None  # the first person always fits
    return Canvas(
        canvas,
        np.stack(joints).astype(np.float32),
        np.stack(located),
        np.array(sources_kept),
        np.array(fractions),
    )


def _cut(patch, points, located, side: int, share: float):
    """The patch without a band through its person: on `side` (0 left, 1 right, 2 top,
    3 bottom), `share` of the located joints' extent along that axis. Returns (patch, points),
    points in the cut patch's pixels (those cut away lie outside it)."""
    low, high = points[located].min(0), points[located].max(0)
    axis = 0 if side < 2 else 1
    depth = share * (high - low)[axis]
    if side in (0, 2):  # the band before `edge` goes
        edge = int(np.ceil(low[axis] + depth))
        patch = patch[:, edge:] if axis == 0 else patch[edge:]
        return np.ascontiguousarray(patch), points - np.eye(2)[axis] * edge
    edge = int(high[axis] - depth)
    return np.ascontiguousarray(patch[:, :edge] if axis == 0 else patch[:edge]), points


def empty_canvas(
    annotations: PoseAnnotations, source: int, size: tuple[int, int] = CANVAS
) -> Canvas | None:
    """A canvas without people: the widest band of LSP image `source` beside its person's box
    (joints' box with a margin of 15 % of its longer side), cropped to the canvas's aspect and
    scaled to fill it; None when no band is EMPTY_MIN_PX wide."""
    width, height = size
    image = read_image(annotations.image_paths[source])
    joints = annotations.joints[source][annotations.located[source]]
    margin = 0.15 * np.ptp(joints, axis=0).max()
    x0, y0 = np.maximum(joints.min(0) - margin, 0).astype(int)
    x1, y1 = np.ceil(joints.max(0) + margin).astype(int)
    bands = [image[:, :x0], image[:, x1:], image[:y0], image[y1:]]

    def fitted(band: np.ndarray) -> np.ndarray:  # cropped to the canvas's aspect, centred
        bh, bw = band.shape[:2]
        cw, ch = min(bw, int(bh * width / height)), min(bh, int(bw * height / width))
        top, left = (bh - ch) // 2, (bw - cw) // 2
        return band[top : top + ch, left : left + cw]

    best = max((fitted(b) for b in bands), key=lambda b: b.shape[0] * b.shape[1])
    if min(best.shape[:2]) < EMPTY_MIN_PX:
        return None
    canvas = cv2.resize(best, size, interpolation=cv2.INTER_LINEAR)
    nobody = np.zeros((0, 14))
    return Canvas(
        canvas, nobody[..., None].repeat(2, -1), nobody > 0, np.zeros(0, int), nobody[:, 0]
    )


def _fit_patch(patch, points, located, size):
    """Crop a scaled image to at most the canvas size, around its person: (patch, points)."""
    width, height = size
    ph, pw = patch.shape[:2]
    centre = (points[located].min(0) + points[located].max(0)) / 2
    x0 = int(np.clip(centre[0] - width / 2, 0, max(pw - width, 0)))
    y0 = int(np.clip(centre[1] - height / 2, 0, max(ph - height, 0)))
    patch = patch[y0 : y0 + height, x0 : x0 + width]
    return np.ascontiguousarray(patch), points - np.array([x0, y0])


def people_of(split: str, start: int = 0) -> PoseAnnotations:
    """The people canvases are built from: LSP's split ("train", "test") or "lspet" (those of
    its people with every joint annotated), after the first `start` images."""
    annotations = load_lspet() if split == "lspet" else load_lsp(split=split)
    annotations = annotations.subset(range(start, len(annotations.image_paths)))
    if split == "lspet":
        annotations = annotations.subset(np.flatnonzero(annotations.located.all(-1)))
    return annotations


def protocol(
    annotations: PoseAnnotations, count: int, seed: int = 0, empty: float = 0.0, cut: float = 0.0
) -> list[Canvas]:
    """`count` canvases of 1-3 people each, every person's size drawn uniformly from one of
    SIZE_BINS (the bin too), people drawn without replacement from `annotations`; a share
    `empty` of the canvases without people (empty_canvas), each person cut by the canvas's edge
    with probability `cut` (compose's cuts: CUT_SIDES, CUT_SHARE)."""
    rng = np.random.default_rng(seed)
    # The draws of the harder kinds, apart: with empty = cut = 0 the canvases stay the same.
    kinds = np.random.default_rng([seed, 1])
    order = rng.permutation(len(annotations.image_paths))
    canvases, next_person = [], 0
    for _ in range(count):
        if empty and kinds.random() < empty:
            nobody = None
            while nobody is None:
                nobody = empty_canvas(annotations, int(order[next_person % len(order)]))
                next_person += 1
            canvases.append(nobody)
            continue
        n = int(rng.integers(1, 4))
        sources = [int(order[(next_person + i) % len(order)]) for i in range(n)]
        next_person += n
        heights = [float(rng.uniform(*SIZE_BINS[rng.integers(len(SIZE_BINS))])) for _ in sources]
        # the largest first: it fills the background and the small ones fit around it
        ranked = sorted(zip(heights, sources, strict=True), reverse=True)
        cuts = [
            (int(kinds.choice(4, p=CUT_SIDES)), float(kinds.uniform(*CUT_SHARE)))
            if cut and kinds.random() < cut
            else None
            for _ in sources
        ]
        people = [s for _, s in ranked], [h for h, _ in ranked]
        canvases.append(compose(annotations, *people, rng, cuts=cuts if cut else None))
    return canvases
