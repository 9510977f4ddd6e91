"""Finding people in a whole image, at any size: where the 2D stage's crops come from when the
caller gives no box.

The joint network runs over a pyramid of the image wide enough for people from
SearchParams.min_height to max_height of the image height; on each level the PSM's upward pass
(ds3d.image2d.psm.RootScores) scores every root position, and its local maxima are people (the
PSM as an articulated-person detector). The network's raw logits are the unaries here, not its
per-map softmax: the softmax shares one unit of probability among everybody in the image, the
logits score each person on its own, comparably across images and levels. The proposals of all
levels then go through non-maximum suppression (ds3d.boxes.suppress) on their pose's boxes.

An image asked for its best person alone is searched from its finer levels first: where their
best proposal frames the image (frames_image), the coarsest level, which seeks the largest
people, is left out. In a photo framed around one person the finer levels' proposal is the best
one nearly always (on 95 % of LSP train's held-out images), and the coarsest level costs about
a quarter of the search's time (docs/tuning.md, speed).

The proposals only say where and how large people are: each is then estimated in its box by
the full 2D stage (ds3d.people.finder), and the person score (ds3d.people.score) says how likely
each pose is a person.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ds3d.boxes import person_boxes, suppress
from ds3d.errors import DataFormatError
from ds3d.image2d.buckets import bucket
from ds3d.image2d.crops import image_share, resize_image
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.features import lab_channels
from ds3d.image2d.jointnet import (
    STRIDE,
    ScaledLogits,
    logits_to_grid,
    padded_logits_each,
)
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PSM_CALL_COST, PairwiseMixtures, RootScores, no_joint_beyond
from ds3d.util.groups import padded_groups
from ds3d.util.threads import map_on_threads, split_rows

# The people a level of person extent E finds: about 0.7 E to 1.3 E, the zoom the joint network
# was trained with (ds3d.training.jointnet.ZOOM).
LEVEL_REACH = (0.7, 1.3)
# The levels' network input is padded to buckets of this many sizes per octave of each side
# (jointnet.padded_logits_each): twice the crops' (jointnet.NET_BUCKET_STEPS), a twentieth
# fewer px for a few more input shapes.
SEARCH_BUCKET_STEPS = 8


@dataclass(frozen=True)
class SearchParams:
    """How the whole-image search runs (chosen on LSP train's held-out images:
    docs/RESULTS.md, people in photos).

    min_height, max_height: the people sought, person extent (the longer side of the joints'
        box) as a fraction of the image height.
    min_extent_px: nor any smaller than this many px of the image. The 2D stage sees a person
        at canonical_extent (100 px): a smaller one is upscaled, blurred, and the search's
        pyramid grows with the square of that upscale; in a small image (LSP's are 170 px
        tall) min_height alone asked for 26 px people, a level 2.7 times the image's size
        that cost most of the search. 72 px is min_height of a 480 px photo (the people
        protocol's canvases, whose people it leaves as they were); 64 px made an LSP image's
        finest level 1.1 times its size, the search 1.2-1.4 times as slow
        (docs/tuning.md).
    level_ratio: the person extent of one pyramid level over the previous one's.
    psm_stride: px of the working scale per PSM cell (the network's maps max-pooled to it).
    peak_radius: cells; a root score is a proposal where it is the maximum within the radius.
    peaks_per_level: at most this many proposals per level.
    overlap: IoU above which the lesser of two proposals (or of two people) is dropped.
    same_person_radius, same_person_joints: two people answered are one, and the lesser
        dropped, where at least same_person_joints of their joints lie within
        same_person_radius times the larger one's extent of each other
        (ds3d.people.same_person.shared_joints): a whole pose and a partial one of the same
        person overlap by less than `overlap` but share joints, which people side by side do
        not.
    on_bones_radius, on_bones_joints: two people answered are one, too, where at least
        on_bones_joints of one's joints lie within on_bones_radius times the larger one's
        extent of the other's bones (ds3d.people.same_person.joints_on_bones): a second
        reading of a body found, drawn along its limbs (a leg read as a whole person, a pose
        turned end to end). People side by side keep their joints off each other's bones: at
        0.035 and 9, LSP train's poses beside each other, their boxes overlapping, are one
        person for no more than 0.6 % of pairs beyond those that same_person_joints joins
        (docs/tuning.md).
    max_people: at most this many proposals per image scoring proposal_floor go on to the
        full 2D stage (asked for its best person alone, an image sends its best proposal).
    whole_image_cover: where the search proposes at most one person, the whole image goes
        through the 2D stage as one more crop (it finds people the image's edge cuts) unless
        the proposal's crop (crops.crop_region) holds at least this fraction of it: in a photo
        that is a tight crop around its person (LSP's) both are that person, estimated twice.
        Such a proposal scoring proposal_floor frames the image (frames_image): an image asked
        for its best person is then not searched at its coarsest level.
    proposal_floor: proposals whose root score is below it do not (the best one always does),
        unless weak:
    weak_floor, weak_people, weak_overlap: the best weak_people of the proposals scoring
        weak_floor to proposal_floor go on to the 2D stage too, and are answered only where
        their pose's box overlaps nobody answered by more than weak_overlap (IoU): on a coarse
        level's maps large people often score below the floor, while the crop poses them well;
        a weak proposal near a person found is mostly a second reading of them.
    weak_apart: so the weak proposals go through the 2D stage after the others, and only those
        whose box (widened as ds3d.boxes.person_boxes widens a pose's) overlaps nobody the
        others answered by more than weak_apart (IoU; PeopleFinder.pose_and_answer): looser
        than weak_overlap, as a proposal's box is not yet its pose's. On the held-out canvases
        about half the weak proposals are then not posed (1.6 of 3.3 a canvas posed), and the
        people answered are the same (docs/tuning.md).
    beyond_edge: how far each level reaches past the image's edges, as a fraction of the
        person extent it seeks: zeros there to the joint network, which learnt where the joints
        a photo cuts off lie (ds3d.training.jointnet.edge_cut), so that a person the frame cuts
        is proposed with them there (and a crop reaching past the edge, InferenceParams.
        beyond_edge), where the PSM could only squeeze them inside. Not further: in photos that
        are tight crops around their person, proposals then reach past the edges more often
        than people do (docs/tuning.md).
    """

    min_height: float = 0.15
    max_height: float = 1.2
    min_extent_px: float = 72.0
    level_ratio: float = 1 / 0.6
    psm_stride: int = 8
    peak_radius: int = 3
    peaks_per_level: int = 5
    overlap: float = 0.5
    same_person_radius: float = 0.1
    same_person_joints: int = 3
    on_bones_radius: float = 0.035
    on_bones_joints: int = 9
    max_people: int = 8
    whole_image_cover: float = 0.9
    proposal_floor: float = 120.0
    weak_floor: float = 60.0
    weak_people: int = 4
    weak_overlap: float = 0.05
    weak_apart: float = 0.2
    beyond_edge: float = 0.15


@dataclass
class Proposals:
    """People proposed in one image, best first: poses (N, 14, 2) px of the image, scores (N,)
    the PSM root scores on the network's logits (higher = surer, not a probability); levels:
    the network's maps of every level searched, which the 2D stage reads its crops' maps off
    rather than running the network again."""

    poses: np.ndarray
    scores: np.ndarray
    levels: list[ScaledLogits]


def level_extents(height: int, params: SearchParams) -> list[float]:
    """Person extents (px of the image), one per pyramid level, smallest first: from the one
    whose reach starts at the smallest person sought (min_height * height, at least
    min_extent_px) up to the first whose reach ends past max_height * height; none where
    that largest person is smaller than the smallest."""
    low, high = LEVEL_REACH
    smallest = max(params.min_height * height, params.min_extent_px)
    largest = params.max_height * height
    if largest < smallest:
        return []
    first = smallest / low
    count = math.ceil(math.log(largest / (first * high)) / math.log(params.level_ratio))
    return [first * params.level_ratio**k for k in range(max(count, 0) + 1)]


def local_peaks(scores: torch.Tensor, radius: int, count: int) -> torch.Tensor:
    """The best `count` local maxima of a map: scores (H, W) -> (K, 2) long cells (x, y), K <=
    count, best first; a cell is a maximum when no cell within `radius` (a square) is higher."""
    pooled = F.max_pool2d(scores[None, None], 2 * radius + 1, 1, radius)[0, 0]
    values = torch.where(scores >= pooled, scores, -torch.inf).flatten()
    top = values.topk(min(count, values.numel()))
    found = top.indices[torch.isfinite(top.values)]
    width = scores.shape[1]
    return torch.stack((found % width, found // width), -1)


def propose(
    estimator: PoseEstimator2D,
    images: list[np.ndarray],
    params: SearchParams,
    best_only: Sequence[bool] | None = None,
    timings: dict[str, float] | None = None,
) -> list[Proposals]:
    """The people of each of B images (H_i, W_i, 3) uint8 RGB, checked (ds3d.inputs): the search
    of the module docstring, the images split over torch.get_num_threads() threads as in
    PoseEstimator2D.estimate, on the estimator's device. best_only: B flags, the images asked
    for their best person alone, whose coarsest level is searched only where the others found
    nobody framing the image (default: none). timings: where given, timings["jointnet"] grows
    by the seconds of the joint network's passes, summed over the threads. Raises
    DataFormatError for a model without a joint network."""
    jointnet = estimator.network
    if jointnet is None:
        raise DataFormatError("the search for people needs the joint network")
    best = list(best_only) if best_only is not None else [False] * len(images)

    def run(rows: torch.Tensor) -> tuple[list[Proposals], float]:
        part = rows.tolist()
        return _propose(
            jointnet,
            estimator.mixtures,
            [images[i] for i in part],
            [best[i] for i in part],
            estimator.params,
            params,
        )

    parts = map_on_threads(run, split_rows(len(images), estimator.device)) if images else []
    if timings is not None:
        timings["jointnet"] = timings.get("jointnet", 0.0) + sum(s for _, s in parts)
    return [found for part, _ in parts for found in part]


def _propose(
    net: nn.Module,
    mixtures: PairwiseMixtures,
    images: list[np.ndarray],
    best_only: list[bool],
    model: EstimatorParams,
    params: SearchParams,
) -> tuple[list[Proposals], float]:
    """propose() on the calling thread, in up to two rounds: every level of each image, but the
    coarsest of an image asked for its best person; then that coarsest level where the others
    found nobody framing the image (frames_image). model: the 2D model's parameters
    (canonical_extent, px of a person at the working scale; unary_weight, the PSM's weight on
    its unaries). Returns the proposals and the seconds of the joint network's passes."""
    extents = [level_extents(image.shape[0], params) for image in images]
    first = [
        e[:-1] if best and len(e) > 1 else e for e, best in zip(extents, best_only, strict=True)
    ]
    found, network_s = _levels_people(net, mixtures, images, first, model, params)
    proposals = [_suppressed(*image, params) for image in found]
    later = [
        i
        for i, image in enumerate(images)
        if len(first[i]) < len(extents[i]) and not frames_image(proposals[i], image, model, params)
    ]
    if later:
        coarsest = [extents[i][-1:] for i in later]
        more, more_s = _levels_people(
            net, mixtures, [images[i] for i in later], coarsest, model, params
        )
        network_s += more_s
        for i, (more_poses, more_scores, more_views) in zip(later, more, strict=True):
            poses, scores, views = found[i]
            proposals[i] = _suppressed(
                poses + more_poses, scores + more_scores, views + more_views, params
            )
    return proposals, network_s


def frames_image(
    proposals: Proposals, image: np.ndarray, model: EstimatorParams, params: SearchParams
) -> bool:
    """Whether the best proposal is a person the image is framed around: scoring proposal_floor,
    with a crop (ds3d.image2d.crops.crop_region of its joints' box) that holds at least
    whole_image_cover of the image. Such a photo's best person is theirs; the pyramid's coarsest
    level, which seeks people up to max_height of the image, would add its time and little else
    (docs/tuning.md, speed)."""
    if not len(proposals.scores) or proposals.scores[0] < params.proposal_floor:
        return False
    pose = proposals.poses[0]
    box = np.concatenate([pose.min(0), pose.max(0)])
    height, width = image.shape[:2]
    return image_share(box, width, height, model) >= params.whole_image_cover


_LevelPeople = tuple[list[np.ndarray], list[np.ndarray], list[ScaledLogits]]


def _levels_people(
    net: nn.Module,
    mixtures: PairwiseMixtures,
    images: list[np.ndarray],
    extents: list[list[float]],
    model: EstimatorParams,
    params: SearchParams,
) -> tuple[list[_LevelPeople], float]:
    """The people of N images at the person extents given for each (level_extents, or some of
    them), before suppression: per image, per level, the poses (K_l, 14, 2) px of the image,
    their root scores (K_l,) and the network's maps (ScaledLogits); and the seconds the network
    took. The levels of all images go through the network together (jointnet.padded_logits_each)
    and their PSMs in groups of near shapes (level_people), so that neither runs one small level
    at a time."""
    pool = max(params.psm_stride // STRIDE, 1)
    poses: list[list[np.ndarray]] = [[] for _ in images]
    scores: list[list[np.ndarray]] = [[] for _ in images]
    views: list[list[ScaledLogits]] = [[] for _ in images]
    levels, labs, beyond = level_inputs(images, extents, model, params, mixtures.mean.device)
    if not levels:
        return list(zip(poses, scores, views, strict=True)), 0.0
    started = time.perf_counter()
    logits = padded_logits_each(net, labs, margin=beyond, steps=SEARCH_BUCKET_STEPS)
    network_s = time.perf_counter() - started
    grids = []
    for lg, (_, resized) in zip(logits, levels, strict=True):
        grid = logits_to_grid(
            lg, resized.shape[0] + 2 * beyond, resized.shape[1] + 2 * beyond, STRIDE, margin=0
        )
        grid = F.max_pool2d(grid, pool, ceil_mode=True)
        # Cells past the level's reach are -inf: no root or joint can score there.
        rows, cols = grid.shape[-2:]
        grids.append(no_joint_beyond(grid, bucket(rows), bucket(cols)))
    unaries = [g * model.unary_weight for g in grids]
    found = level_people(unaries, mixtures, STRIDE * pool, params)
    for (i, resized), lg, (pose, score) in zip(levels, logits, found, strict=True):
        height, width = images[i].shape[:2]
        scale = (resized.shape[1] / width, resized.shape[0] / height)
        views[i].append(ScaledLogits(lg, scale, beyond))
        pose = (pose - beyond) / np.array(scale)
        # A person the image shows: at least half of the joints within it.
        shown = ((pose >= 0) & (pose < (width, height))).all(-1).mean(-1) >= 0.5
        poses[i].append(pose[shown])
        scores[i].append(score[shown])
    return list(zip(poses, scores, views, strict=True)), network_s


def level_inputs(
    images: list[np.ndarray],
    extents: Sequence[Sequence[float]],
    model: EstimatorParams,
    params: SearchParams,
    device: torch.device,
) -> tuple[list[tuple[int, np.ndarray]], list[torch.Tensor], int]:
    """The pyramid levels of N images (H_i, W_i, 3) uint8 RGB at the person extents given for
    each (px of the image; level_extents'): per level, (the image's index,
    the image resized to it, (h, w, 3)), its Lab / 100 channels (1, 3, h, w) on `device`, and
    the px of zeros the levels reach past the images' edges (beyond_edge, whole network
    cells), which the network's input carries round them (padded_logits_each's margin). A
    level smaller than a few PSM cells is left out."""
    canonical_extent = model.canonical_extent
    pool = max(params.psm_stride // STRIDE, 1)
    levels = []
    for i, (image, sought) in enumerate(zip(images, extents, strict=True)):
        for extent in sought:
            resized = resize_image(image, canonical_extent / extent)
            if min(resized.shape[:2]) >= 2 * STRIDE * pool:
                levels.append((i, resized))
    # The network's border of zeros (jointnet.MARGIN) is the levels' reach past the edges, no
    # more; and their inputs' buckets are finer than the crops' (SEARCH_BUCKET_STEPS): the
    # search's maps are most of a searched image's network time (docs/tuning.md, speed).
    beyond = round(params.beyond_edge * canonical_extent / STRIDE) * STRIDE
    labs = [lab_channels(torch.from_numpy(r).to(device)[None]) for _, r in levels]
    return levels, labs, beyond


def level_people(
    unaries: list[torch.Tensor], mixtures: PairwiseMixtures, stride: int, params: SearchParams
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The people of each level: unaries (1, 14, h_i, w_i) the PSM's, stride px of the level per
    cell -> per level, poses (K, 14, 2) px of the level and root scores (K,), the best local
    maxima of the root scores (local_peaks). Levels of near shapes share one PSM, padded with
    -inf, where no root or joint can score (padded_groups): small maps cost a PSM its fixed
    ops more than their cells."""
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for rows in padded_groups([(u.shape[-2], u.shape[-1]) for u in unaries], PSM_CALL_COST):
        height = max(unaries[i].shape[-2] for i in rows)
        width = max(unaries[i].shape[-1] for i in rows)
        group = [no_joint_beyond(unaries[i], height, width) for i in rows]
        upward = RootScores(torch.cat(group), mixtures, stride=float(stride))
        radius, most = params.peak_radius, params.peaks_per_level
        peaks = [local_peaks(root, radius, most) for root in upward.root]
        # The levels' peaks padded to one count with each level's first, then cut back.
        count = max(len(p) for p in peaks)
        padded = torch.stack([torch.cat([p, _first(p).expand(count - len(p), 2)]) for p in peaks])
        found = upward.poses(padded)
        for k, (i, p) in enumerate(zip(rows, peaks, strict=True)):
            n = len(p)
            out[i] = (
                found.joints_2d[k, :n].cpu().numpy(),
                found.score[k, :n].float().cpu().numpy(),
            )
    return [out[i] for i in range(len(unaries))]


def _first(peaks: torch.Tensor) -> torch.Tensor:
    """(1, 2) the first of (K, 2) peak cells, or cell (0, 0) where there are none."""
    return peaks[:1] if len(peaks) else peaks.new_zeros(1, 2)


def _suppressed(
    poses: list[np.ndarray],
    scores: list[np.ndarray],
    levels: list[ScaledLogits],
    params: SearchParams,
) -> Proposals:
    """One image's Proposals from its levels' poses (K_l, 14, 2) px of the image and root
    scores (K_l,): non-maximum suppression over all levels."""
    if not poses:
        return Proposals(np.zeros((0, 14, 2), np.float32), np.zeros(0, np.float32), levels)
    poses_all, scores_all = np.concatenate(poses), np.concatenate(scores)
    kept = suppress(person_boxes(poses_all), scores_all, params.overlap)
    return Proposals(poses_all[kept].astype(np.float32), scores_all[kept], levels)
