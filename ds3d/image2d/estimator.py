"""Image -> 2D pose: scale normalisation, a 6-scale pyramid, the forest cascade for the unaries
(ds3d.image2d.cascade), the joint network as a second unary (ds3d.image2d.jointnet), and the
pictorial structure model (ds3d.image2d.psm) on each scale.

Working scale. Training rescales every image so that the person's extent (the longer side of
the box around its joints) is `canonical_extent` pixels; the PSM's offsets are learnt at that
scale. At inference an image (or a person box, ds3d.image2d.crops) is first resized to a base
scale where a person filling it would have that extent, and the pyramid holds `n_scales` scales
`start * factor**k` around it. Each image's scale is chosen first (InferenceParams.scale_choice):
by the extent of the joint network's pose at the base scale, or by a coarse pass of the forests
(`select_stride`, every 6th pixel, the first `coarse_trees` trees of each layer) over every
scale; only the chosen scale then runs at the full `stride` with every tree.

Joint network. In the final pass its log-probabilities join the cascade's (weighted by
`jointnet_weight`; ds3d.image2d.left_right); the coarse pass that picks the scale reads the
cascade alone. The PSM's MAP lies on the grid of evaluated pixels; each of its joints then moves
to the centroid of its unary map around it (psm.local_centroid, InferenceParams.joint_cells).

Left and right are settled per image by ds3d.image2d.left_right, and results are
person-centric like LSP's labels.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ds3d.errors import DataFormatError
from ds3d.image2d.buckets import bucket
from ds3d.image2d.cascade import (
    DEVICE_GROUP_BYTES,
    GROUP_BYTES,
    forest_cells,
    group_channels,
    group_unaries,
    traversal_groups,
)
from ds3d.image2d.crops import Crop, resize_image, working_crops
from ds3d.image2d.facing import FacingNet
from ds3d.image2d.features import lab_channels
from ds3d.image2d.forest import Forest
from ds3d.image2d.jointnet import (
    STRIDE,
    JointNet,
    ScaledLogits,
    jointnet_unaries,
    logits_to_grid,
    padded_logits_each,
    read_logits,
    unaries_from_logits,
)
from ds3d.image2d.left_right import facing_probability, person_centric, settle_left_right
from ds3d.image2d.model_files import load_model
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures, infer
from ds3d.image2d.result import Estimate2D, gather_rows, keep_better, pad_maps
from ds3d.util.paths import MODELS_DIR, require_models
from ds3d.util.threads import map_on_threads, split_rows


class PoseEstimator2D:
    """Image -> 2D pose with the trained cascade and PSM of a model directory.

    Load with PoseEstimator2D.load(model_dir) (default: models/image2d); the directory holds
    manifest.json (params, layer files), forest1.pt.gz, forest2.pt.gz, ..., psm.pt and the
    facing model facing.pt (ds3d.image2d.facing).
    """

    def __init__(
        self,
        layers: list[Forest],
        mixtures: PairwiseMixtures,
        params: EstimatorParams,
        facing: FacingNet | None = None,
        jointnet: JointNet | None = None,
        jointnet_int8: nn.Module | None = None,
    ):
        if params.observer_labels and facing is None and jointnet is None and layers:
            raise DataFormatError("observer-centric labels need a facing model or joint network")
        self.layers = layers
        self.mixtures = mixtures
        self.params = params
        self.facing = facing
        self.jointnet = jointnet
        self.jointnet_int8 = jointnet_int8  # the CPU's copy (ds3d.image2d.quantized)
        self._layers_of: dict[int, list[Forest]] = {}  # the layers cut short, per tree count

    @property
    def device(self) -> torch.device:
        """Where the model lives and the 2D stage runs (PoseEstimator2D.to)."""
        return self.mixtures.mean.device

    def to(self, device: torch.device | str) -> PoseEstimator2D:
        """The estimator with every part of its model on `device`: the images go there once
        their crops are resized (on the CPU, with OpenCV), and every step of estimate() runs
        there (and of the search for people, ds3d.people.search; off the CPU with the float
        joint network, the int8 copy being the CPU's)."""
        on_cpu = torch.device(device).type == "cpu"
        return PoseEstimator2D(
            [forest.to(device) for forest in self.layers],
            self.mixtures.to(device),
            self.params,
            None if self.facing is None else self.facing.to(device),
            None if self.jointnet is None else self.jointnet.to(device),
            self.jointnet_int8 if on_cpu else None,
        )

    @property
    def network(self) -> nn.Module | None:
        """The joint network that runs: the int8 copy where the model has one and this machine
        runs it faster (ds3d.image2d.quantized), else the float one (None: the model has
        none)."""
        return self.jointnet_int8 if self.jointnet_int8 is not None else self.jointnet

    @classmethod
    def load(cls, model_dir: Path | str | None = None, device: str = "cpu") -> PoseEstimator2D:
        """The model in `model_dir` (default: models/image2d; ds3d.image2d.model_files) on
        `device` (PoseEstimator2D.to). Raises DataFormatError when it is missing or
        malformed."""
        model_dir = Path(model_dir) if model_dir is not None else MODELS_DIR / "image2d"
        model = load_model(require_models(model_dir))
        estimator = cls(
            model.layers,
            model.mixtures,
            model.params,
            model.facing,
            model.jointnet,
            model.jointnet_int8,
        )
        return estimator if torch.device(device).type == "cpu" else estimator.to(device)

    def scales(self) -> list[float]:
        p = self.params
        return [p.scale_start * p.scale_factor**k for k in range(p.n_scales)]

    def estimate(
        self,
        images: list[np.ndarray],
        bboxes: list | None = None,
        scales: list[float] | None = None,
        views: list[Sequence[ScaledLogits]] | None = None,
    ) -> Estimate2D:
        """2D poses of a batch of images.

        images: B arrays (H_i, W_i, 3) uint8 RGB; bboxes: None or B entries, each None or a
        person box (x0, y0, x1, y1) in image pixels (the region around it is cropped first),
        as checked where they entered (ds3d.inputs).
        scales: pyramid scales relative to the base scale (default: the model's 6).
        views: None or B entries, the joint network's maps of each image at some scales (the
        search's levels, ds3d.people.search.Proposals.levels): where the network chooses a
        crop's scale, the maps it reads are read off them (jointnet.read_logits) when one is
        near enough in scale, not computed again. (Read so for the final pass too, they cost
        2.9 points of PCK on LSP train's held-out images searched: a view's scale is up to 1.3
        times off.)
        Returns Estimate2D (joints in each input image's pixels).

        Each image's scale is chosen by InferenceParams.scale_choice, and only the chosen scale
        is run at `stride` (with "every", every scale is, and the best PSM score wins).

        With torch.get_num_threads() = N > 1, the batch is split into N parts run at once on N
        threads of one intra-op thread each: the traversal's gathers do not parallelise within
        an op, but whole images do (docs/RESULTS.md, 2D stage speed;
        ds3d.util.threads). Each image's result does not depend on the batch it is in, so neither
        does it on N. The step timings are then summed over the threads (CPU seconds); "total"
        is wall-clock.
        """
        if len(images) == 0:
            raise ValueError("no images")
        if bboxes is not None and len(bboxes) != len(images):
            raise ValueError(f"{len(bboxes)} bboxes for {len(images)} images")
        t_start = time.perf_counter()
        crops = working_crops(images, bboxes, self.params)
        if views is not None:
            crops = [replace(c, views=v) for c, v in zip(crops, views, strict=True)]
        scales = list(scales) if scales is not None else self.scales()
        parts = split_rows(len(crops), self.device)
        results = map_on_threads(
            lambda rows: self._estimate_crops([crops[i] for i in rows], scales), parts
        )
        if len(parts) == 1:
            best = results[0]
        else:
            best = gather_rows(list(zip(parts, results, strict=True)), len(crops))
        timings = {k: round(v, 6) for k, v in best.timings.items()}
        best = person_centric(best)
        best.timings = {**timings, "total": round(time.perf_counter() - t_start, 6)}
        return best

    def _estimate_crops(self, crops: list[Crop], scales: list[float]) -> Estimate2D:
        """estimate() of crops on the calling thread, before the left/right decision; sets
        timings of the steps (seconds)."""
        p = self.params
        timings = {"features": 0.0, "traversal": 0.0, "jointnet": 0.0, "psm": 0.0}
        with_net = self.network is not None and p.jointnet_weight > 0
        full = self._first_trees(p.trees)  # the full pass's layers
        if len(scales) > 1 and p.scale_choice == "network" and with_net:
            choice, base, logits = self._network_scales(crops, scales, timings)
            best = self._chosen_scales(crops, scales, choice, full, timings, base, logits)
        elif len(scales) == 1 or p.scale_choice == "every":
            best = self._one_scale(crops, scales[0], full, p, timings)
            for rel in scales[1:]:
                best = keep_better(best, self._one_scale(crops, rel, full, p, timings))
        else:
            # The coarse pass blurs its unaries over the same pixels (at least one cell).
            coarse = replace(
                p,
                stride=p.select_stride,
                unary_blur=max(1, round(p.unary_blur * p.stride / p.select_stride)),
                flip_test=False,
            )
            layers = self._first_trees(p.coarse_trees)
            score = torch.stack(
                [
                    self._one_scale(crops, rel, layers, coarse, timings, final=False).score
                    for rel in scales
                ]
            )
            choice = score.argmax(dim=0).cpu()  # (B,) index into scales
            best = self._chosen_scales(crops, scales, choice, full, timings)
        best.timings = timings
        return best

    def _chosen_scales(
        self,
        crops: list[Crop],
        scales: list[float],
        choice: torch.Tensor,
        layers: list[Forest],
        timings: dict[str, float],
        base: int | None = None,
        base_logits: list[torch.Tensor] | None = None,
    ) -> Estimate2D:
        """The full pass of each crop at its chosen scale, choice (B,) an index into scales:
        one _one_scale per scale chosen, on its crops. base_logits: each crop's padded_logits
        at scales[base], reused by the crops whose choice is the base."""
        parts = []
        for k in choice.unique().tolist():
            rows = torch.nonzero(choice == k).view(-1)
            reuse = None
            if k == base and base_logits is not None:
                reuse = [base_logits[i] for i in rows.tolist()]
            part = self._one_scale(
                [crops[i] for i in rows], scales[k], layers, self.params, timings, logits=reuse
            )
            parts.append((rows, part))
        return gather_rows(parts, len(crops))

    def _network_scales(
        self, crops: list[Crop], scales: list[float], timings: dict[str, float]
    ) -> tuple[torch.Tensor, int, list[torch.Tensor]]:
        """Each crop's pyramid scale from the joint network at the base scale (the scale of
        `scales` nearest 1): the extent of the PSM's pose on its maps alone says how far the
        person is from the canonical extent (nearest_scale). Returns the choice (B,) index into
        scales, the base's index, and each crop's padded_logits at the base scale, for the
        full pass to reuse where the base is chosen (elsewhere the network runs again: its
        maps at the chosen scale are worth half a point, docs/tuning.md). A crop with views
        (the search's maps of its image) reads its base maps off the nearest (read_logits)
        rather than running the network."""
        p, jointnet = self.params, self.network
        assert jointnet is not None, "the scales are chosen by the joint network"
        base = min(range(len(scales)), key=lambda k: abs(math.log(scales[k])))
        t0 = time.perf_counter()
        resized = [resize_image(c.image, c.base * scales[base]) for c in crops]
        t1 = time.perf_counter()
        read = [_read_logits(crop, image) for crop, image in zip(crops, resized, strict=True)]
        missing = [i for i, r in enumerate(read) if r is None]
        labs = [lab_channels(self._upload(resized[i])) for i in missing]
        computed = dict(zip(missing, padded_logits_each(jointnet, labs), strict=True))
        logits = [computed[i] if r is None else r for i, r in enumerate(read)]
        grids = [
            logits_to_grid(lg, r.shape[0], r.shape[1], STRIDE)
            for lg, r in zip(logits, resized, strict=True)
        ]
        t2 = time.perf_counter()
        gh, gw = (bucket(max(g.shape[k] for g in grids)) for k in (2, 3))
        unaries = torch.cat([pad_maps(unaries_from_logits(g), gh, gw) for g in grids])
        pose = infer(unaries * p.unary_weight, self.mixtures, stride=float(STRIDE)).joints_2d
        extent = (pose.amax(1) - pose.amin(1)).amax(-1).cpu()  # (B,) px at the base scale
        choice = nearest_scale(p.canonical_extent / extent * scales[base], scales)
        timings["features"] += t1 - t0
        timings["jointnet"] += t2 - t1
        timings["psm"] += time.perf_counter() - t2
        return choice, base, logits

    @property
    def _group_bytes(self) -> int:
        """The bytes of a traversal group on the estimator's device (cascade.traversal_groups)."""
        return GROUP_BYTES if self.device.type == "cpu" else DEVICE_GROUP_BYTES

    def _upload(self, image: np.ndarray) -> torch.Tensor:
        """(H, W, 3) uint8 -> (1, H, W, 3) on the estimator's device."""
        return torch.from_numpy(image).to(self.device)[None]

    def _first_trees(self, k: int | None) -> list[Forest]:
        """The layers cut to their first k trees (None: all), made once per k (a new Forest
        converts its node reads again, Forest.node_table)."""
        if k is None:
            return self.layers
        if k not in self._layers_of:
            self._layers_of[k] = [forest.first_trees(k) for forest in self.layers]
        return self._layers_of[k]

    def _one_scale(
        self,
        crops: list[Crop],
        rel: float,
        layers: list[Forest],
        p: EstimatorParams,
        timings: dict[str, float],
        final: bool = True,
        logits: list[torch.Tensor] | None = None,
    ) -> Estimate2D:
        """Cascade (`layers`) + PSM of every crop at `rel` times its base scale, with params p
        (whose stride and blur may differ from the model's); adds the seconds of each step to
        timings. final: whether this pass answers, so runs the joint network (its unaries are
        added to the cascade's, settle_left_right) or else the facing model (the coarse
        pass only needs the cascade's scores; its facing_camera is then 1). logits: the joint
        network's padded_logits of each crop at this scale where already computed. The cascade and
        the PSM run on groups of images of similar shape (traversal_groups), each padded to its
        group's largest."""
        t0 = time.perf_counter()
        resized = [resize_image(c.image, c.base * rel) for c in crops]
        sizes = [r.shape[:2] for r in resized]
        timings["features"] += time.perf_counter() - t0
        groups = [
            self._group_pose(resized, rows, layers, p, timings, final, logits)
            for rows in traversal_groups(sizes, layers[-1], self._group_bytes)
        ]
        # Back to the batch's order, padded to one grid (log(LOG_EPS) outside each image).
        gh = max(g.unaries.shape[2] for _, g in groups)
        gw = max(g.unaries.shape[3] for _, g in groups)
        order = torch.cat([rows for rows, _ in groups]).argsort()

        def batch(get) -> torch.Tensor:
            return torch.cat([get(g) for _, g in groups])[order]

        unaries = batch(lambda g: pad_maps(g.unaries, gh, gw))
        working = batch(lambda g: g.working)
        fac = torch.tensor(
            [
                [r.shape[1] / c.image.shape[1], r.shape[0] / c.image.shape[0]]
                for r, c in zip(resized, crops, strict=True)
            ],
            dtype=torch.float32,
            device=working.device,
        )  # (B, 2) working px per image px, (x, y)
        off = fac.new_tensor([[c.x0, c.y0] for c in crops])
        joints = (working + 0.5) / fac[:, None] - 0.5 + off[:, None]
        affine = fac.new_zeros(len(crops), 2, 3)
        affine[:, 0, 0] = p.stride / fac[:, 0]
        affine[:, 1, 1] = p.stride / fac[:, 1]
        affine[:, :, 2] = 0.5 / fac - 0.5 + off
        return Estimate2D(
            joints,
            batch(lambda g: g.joint_scores),
            batch(lambda g: g.score),
            unaries,
            affine,
            fac.mean(1),
            batch(lambda g: g.faces),
        )

    def _group_pose(
        self,
        images: list[np.ndarray],
        rows: list[int],
        layers: list[Forest],
        p: EstimatorParams,
        timings: dict[str, float],
        final: bool,
        logits: list[torch.Tensor] | None,
    ) -> tuple[torch.Tensor, _GroupPose]:
        """The unaries and PSM pose of the images[rows], one group of _one_scale (arguments as
        there). Returns (rows (b,) long, the group's _GroupPose)."""
        group = [images[i] for i in rows]
        channels, sizes = group_channels(group, timings, self.device)
        jointnet = self.network if final and p.jointnet_weight > 0 else None
        with_net = jointnet is not None
        cells = None
        if jointnet is not None:
            t1 = time.perf_counter()
            known = None if logits is None else [logits[i] for i in rows]
            net = jointnet_unaries(jointnet, channels, sizes, p.stride, p.flip_test, known)
            if p.forest_reach is not None:
                cells = forest_cells(net, p.forest_reach)
            timings["jointnet"] += time.perf_counter() - t1
        unaries = group_unaries(group, channels, layers, self.mixtures, p, timings, cells)
        t1 = time.perf_counter()
        faces = channels.new_ones(len(rows))
        if with_net:  # the joint network's maps settle left and right
            unaries, res, faces = settle_left_right(unaries, net, self.mixtures, p)
            # The centroid sharpens the sum of the two, as the PSM weighs them.
            working = p.joint_cells(unaries * (1 + p.jointnet_weight), res.cells) * p.stride
        else:
            res = infer(unaries * p.unary_weight, self.mixtures, stride=float(p.stride))
            res = replace(res, joint_scores=res.joint_scores / p.unary_weight)  # log-probs
            working = p.joint_cells(unaries, res.cells) * p.stride  # (b, 14, 2) px, working
            if final:
                faces = facing_probability(self.facing, channels, working, sizes)
        timings["psm"] += time.perf_counter() - t1
        pose = _GroupPose(unaries, working, res.joint_scores.float(), res.score.float(), faces)
        return torch.tensor(rows), pose


@dataclass
class _GroupPose:
    """What _group_pose finds for b images: unaries (b, 14, gh, gw) of the group's grid, joints
    (b, 14, 2) px at the working scale, joint scores (b, 14), PSM scores (b,), P(facing)."""

    unaries: torch.Tensor
    working: torch.Tensor
    joint_scores: torch.Tensor
    score: torch.Tensor
    faces: torch.Tensor


def _read_logits(crop: Crop, resized: np.ndarray) -> torch.Tensor | None:
    """The padded_logits of `resized` (the crop's image resized) read off the crop's views
    (jointnet.read_logits); None where it has none near its scale."""
    h, w = resized.shape[:2]
    scale = (w / crop.image.shape[1], h / crop.image.shape[0])
    return read_logits(crop.views, scale, (crop.x0, crop.y0), h, w)


def nearest_scale(wanted: torch.Tensor, scales: list[float]) -> torch.Tensor:
    """wanted (B,) scales (relative to the base) -> (B,) long index of the nearest of `scales`
    in ratio."""
    ratio = torch.log(wanted.clamp_min(1e-6))[:, None] - torch.log(torch.tensor(scales))[None]
    return ratio.abs().argmin(-1)
