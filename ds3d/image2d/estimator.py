"""Image -> 2D pose: scale normalisation, a 6-scale pyramid, a forest cascade for the unaries,
and the pictorial structure model (ds3d.image2d.psm) on each scale.

Working scale. Training rescales every image so that the person's extent (the longer side of
the box around its joints) is `canonical_extent` pixels; the PSM's offsets are learnt at that
scale. At inference an image (or a person box) is first resized to a base scale where a person
filling it would have that extent, then the pyramid tries `n_scales` scales
`start * factor**k` around it and keeps, per image, the scale whose PSM score is best. To save
time, the scale is chosen by a coarse pass (`select_stride`, every 6th pixel; optionally with
only the first `coarse_trees` trees of each layer) over all scales; only the chosen scale is then
run at the full `stride` with every tree.

Cascade. Layer 1 classifies every `stride`-th pixel into 14 joints + background from image
channels. Each later layer (auto-context) splits on the image channels AND on the previous
layer's joint probability maps, read at offsets, which lets it use where the other joints
probably are. Unaries are log(box-blurred probabilities of the last layer).

Joint network. A model may also have a small CNN that scores each joint's position from the
whole person (ds3d.image2d.jointnet). In the final pass its log-probabilities join the
cascade's (weighted by `jointnet_weight`, left_right_hypotheses); the coarse pass that picks the
scale reads the cascade alone. The PSM's MAP lies on the grid of evaluated pixels; each of its
joints then moves to the centroid of its unary map around it (psm.local_centroid,
EstimatorParams.joint_cells).

Left and right. The cascade labels the limb on the image's left "right" in nearly every image,
as if everyone faced the camera. The joint network, trained on person-centric labels, knows
better: the PSM runs with the cascade's maps as they are and with left and right swapped, and
the better score says whether the person faces the camera. Without a joint network, a small
CNN on the image around the PSM's torso (ds3d.image2d.facing) says it. Either way left and right
are swapped at the end where the person faces away, so results are person-centric like LSP's
labels. With `observer_labels` (off in the bundled model) the cascade and the PSM are trained
on observer-centric labels outright (the arm whose shoulder is on the image's left is "right";
see ds3d.image2d.train), and the same decision maps them back.
"""

from __future__ import annotations

import gzip
import io
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from ds3d.errors import DataFormatError, InvalidImage
from ds3d.image2d.facing import FacingNet, faces_camera_probability
from ds3d.image2d.features import NUM_IMAGE_CHANNELS, box_mean, image_channels, pad_channels
from ds3d.image2d.forest import Forest, predict_proba
from ds3d.image2d.jointnet import JointNet, logits_on_grid, spatial_softmax
from ds3d.image2d.psm import PairwiseMixtures, PsmResult, infer, local_centroid
from ds3d.paths import MODELS_DIR
from ds3d.skeleton import FLIP, NUM_JOINTS
from ds3d.threads import map_on_threads, split_rows

LOG_EPS = 1e-4  # floor of the probabilities before the log: keeps unaries finite


@dataclass
class EstimatorParams:
    """Algorithm parameters of the 2D stage (stored in the model's manifest.json)."""

    canonical_extent: float = 100.0  # person extent in px at the working scale
    image_to_extent: float = 1.35  # a full image without a box: its longer side / person extent
    box_to_extent: float = 1.0  # a person box: its longer side / person extent
    box_margin: float = 0.35  # context kept around a box, fraction of the extent per side
    stride: int = 3  # px between evaluated pixels (one unary cell)
    context_blur: int = 1  # box radius (cells) on layer-1 maps before layer 2 reads them
    # Whether a context layer also reads the PSM's MAP pose on the layer before's maps, as one
    # Gaussian heatmap per joint of this sigma (px at the working scale; None: the maps alone).
    # Fixed by training (layer_context). At 6 px: 45.6 % against 44.0 % on the held-out images,
    # 41.4 % against 40.4 % on LSP test, for 1.6-1.9x the 2D stage's time; off in the bundled
    # model (docs/RESULTS.md, its section).
    context_pose_sigma: float | None = None
    unary_blur: int = 2  # box radius (cells) on the final maps before the log
    # The PSM sees unary_weight * unaries (relative to the binaries). With the joint network,
    # 1 / 1.5 / 2 / 3 / 4 / 8 gave 63.7 / 64.4 / 64.5 / 63.3 / 63.1 / 62.4 % PCK@0.2 on the
    # held-out images (jointnet_weight 1, before the network's margin; docs/RESULTS.md). The
    # forests alone were best at 8 (42.9 / 44.0 / 44.0 / 44.0 / 43.6 % at 3 / 6 / 8 / 12 / 16).
    unary_weight: float = 2.0
    # Each joint of the PSM's MAP moves to the centroid of its unary probabilities ^ sharpness
    # within this many cells (psm.local_centroid; None: stays on its cell). On the held-out
    # images, with unary_weight 8: 43.9-44.3 % against 42.1 % without it at weight 4 (the
    # weights and sharpness tried: docs/RESULTS.md).
    centroid_radius: int | None = 2
    centroid_sharpness: float = 4.0
    n_scales: int = 6
    scale_factor: float = 0.85
    scale_start: float = 1.0 / 0.85**2  # the largest pyramid scale, relative to the base
    # A coarse pass at this stride picks each image's scale, then only that scale runs at
    # `stride` (None: every scale at `stride`, the best PSM score wins; 1.5-2x slower).
    select_stride: int | None = 6
    # Trees per layer in the coarse pass (None: all). 8 of 16: 1.3x faster, validation PCK
    # 39.5 vs 40.2 % with the model of the time (docs/RESULTS.md, inference).
    coarse_trees: int | None = 8
    observer_labels: bool = False  # observer-centric cascade + PSM, the facing model decides
    # Whether the full-stride pass averages each image's class probabilities with its mirror
    # image's (mapped back; the coarse pass never does). Off by default: on the held-out images
    # it gained only 0.3 / 0.7 points PSM / argmax PCK, with a 0.16 px worse mean error, for
    # 1.6-1.9x the time of the 2D stage (docs/RESULTS.md).
    flip_test: bool = False
    # Weight of the joint network's unaries (ds3d.image2d.jointnet) against the forests' in the
    # final pass of a model that has one (left_right_hypotheses; 0: the forests alone, as
    # without one). On the held-out images, with unary_weight 2: 1 / 1.5 / 2 (at 1.5) gave
    # 64.8 / 65.6 / 65.6 % PCK@0.2, the network alone about 59 % (docs/RESULTS.md).
    jointnet_weight: float = 1.5

    def joint_cells(self, unaries: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """Where the joints of a PSM MAP go: unaries (B, 14, H, W) log-probabilities the PSM ran
        on, its MAP cells (B, 14, 2) long (x, y) -> (B, 14, 2) float32 cells (x, y), the local
        unary centroids (psm.local_centroid) or, without a centroid radius, the cells."""
        if self.centroid_radius is None:
            return cells.float()
        return local_centroid(unaries, cells, self.centroid_radius, self.centroid_sharpness)


def resize_image(image: np.ndarray, scale: float) -> np.ndarray:
    """(H, W, 3) uint8 -> (round(H * scale), round(W * scale), 3) uint8, area-averaged when
    shrinking. The exact per-axis factors are the ratios of the shapes."""
    h, w = image.shape[:2]
    nh, nw = max(round(h * scale), 1), max(round(w * scale), 1)
    if (nh, nw) == (h, w):
        return image
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(image, (nw, nh), interpolation=interp)


def grid_positions(height: int, width: int, stride: int) -> tuple[torch.Tensor, int, int]:
    """Pixels evaluated on a (height, width) image: (P, 2) int64 (y, x) = (i * stride, j * stride)
    for a (gh, gw) grid, P = gh * gw (row-major). Returns (positions, gh, gw)."""
    ys = torch.arange(0, height, stride)
    xs = torch.arange(0, width, stride)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([yy.reshape(-1), xx.reshape(-1)], dim=1), len(ys), len(xs)


def context_channels(
    maps: torch.Tensor,
    stride: int,
    height: int,
    width: int,
    sizes: list[tuple[int, int]] | None = None,
) -> torch.Tensor:
    """A layer's joint probability maps on the grid -> full-resolution channels by nearest grid
    cell.

    maps: (B, 14, gh, gw); sizes: None (every image fills height x width) or B (h, w) sizes of
    the images in a zero-padded batch: each image's pixels then read only its own cells, as
    alone -> (B, 14, height, width) float32.
    """
    b, _, gh, gw = maps.shape
    if sizes is None:
        last = [(gh - 1, gw - 1)] * b
    else:
        last = [((h - 1) // stride, (w - 1) // stride) for h, w in sizes]
    iy = torch.div(torch.arange(height) + stride // 2, stride, rounding_mode="floor")
    ix = torch.div(torch.arange(width) + stride // 2, stride, rounding_mode="floor")
    # Two index_selects per image: ~3x faster than one advanced index over the whole batch.
    return torch.stack(
        [
            m.index_select(1, iy.clamp(max=ly)).index_select(2, ix.clamp(max=lx))
            for m, (ly, lx) in zip(maps, last, strict=True)
        ]
    )


def pose_heatmaps(cells: torch.Tensor, height: int, width: int, sigma: float) -> torch.Tensor:
    """One Gaussian bump per joint: cells (B, 14, 2) (x, y) on a height x width grid, sigma in
    cells -> (B, 14, height, width) float32, 1 at each joint's cell."""
    ys = torch.arange(height, dtype=torch.float32).view(1, 1, -1, 1)
    xs = torch.arange(width, dtype=torch.float32).view(1, 1, 1, -1)
    dx = xs - cells[..., 0, None, None].float()
    dy = ys - cells[..., 1, None, None].float()
    return torch.exp(-0.5 * (dx * dx + dy * dy) / (sigma * sigma))


def layer_context(
    probs: torch.Tensor, params: EstimatorParams, mixtures: PairwiseMixtures | None
) -> torch.Tensor:
    """What a context layer reads of the layer before it, on the grid: (B, 15, gh, gw) class
    probabilities -> (B, 14, gh, gw) joint maps box-blurred by context_blur, with
    context_pose_sigma followed by (B, 14, gh, gw) heatmaps of the MAP pose of the PSM
    (`mixtures`) on those probabilities' unaries (as the 2D stage weighs them): the trees can
    then split on where the best whole pose puts each joint, not only on each joint's map."""
    maps = box_mean(probs[:, :NUM_JOINTS].float(), params.context_blur)
    if params.context_pose_sigma is None:
        return maps
    if mixtures is None:
        raise ValueError("context_pose_sigma needs the PSM's mixtures")
    unaries = unaries_from_probs(probs.float(), params.unary_blur)
    cells = infer(unaries * params.unary_weight, mixtures, stride=float(params.stride)).cells
    sigma = params.context_pose_sigma / params.stride
    return torch.cat([maps, pose_heatmaps(cells, *maps.shape[-2:], sigma)], dim=1)


def cascade_probs(
    layers: list[Forest],
    channels: torch.Tensor,
    params: EstimatorParams,
    sizes: list[tuple[int, int]] | None = None,
    mixtures: PairwiseMixtures | None = None,
) -> list[torch.Tensor]:
    """Run the forest cascade on a batch.

    channels: (B, 12, H, W) from image_channels, zero outside each image;
    sizes: None (every image fills H x W) or B (h, w) sizes of the images in a zero-padded
    batch: context maps are zeroed outside each image, as around a single image in training;
    mixtures: the PSM's, for layer_context with context_pose_sigma
    -> one (B, 15, gh, gw) class-probability map per layer (joints 0-13, background 14), on the
    grid of grid_positions(H, W, stride).
    """
    b, _, h, w = channels.shape
    positions, gh, gw = grid_positions(h, w, params.stride)
    # In a padded batch, cells outside an image are zeroed: as around a single image.
    inside = None if sizes is None else valid_cells(sizes, h, w, params.stride)
    inside_px = None if sizes is None else valid_cells(sizes, h, w, 1)
    outputs = []
    stack = channels
    for i, forest in enumerate(layers):
        if i > 0:
            context = layer_context(outputs[-1], params, mixtures)
            ctx = context_channels(context, params.stride, h, w, sizes)
            if inside_px is not None:
                ctx = ctx * inside_px
            stack = torch.cat([channels, ctx], dim=1)
        probs = predict_proba(forest, pad_channels(stack, forest.radius), positions)
        probs = probs.permute(0, 2, 1).reshape(b, -1, gh, gw)
        outputs.append(probs if inside is None else probs * inside)
    return outputs


def valid_cells(sizes: list[tuple[int, int]], height: int, width: int, stride: int) -> torch.Tensor:
    """(B, 1, gh, gw) bool: the cells of the grid of grid_positions(height, width, stride) that
    fall inside each image of a zero-padded batch; sizes: B (h, w)."""
    ys = torch.arange(0, height, stride)
    xs = torch.arange(0, width, stride)
    rows = torch.stack([ys < h for h, _ in sizes])  # (B, gh)
    cols = torch.stack([xs < w for _, w in sizes])  # (B, gw)
    return (rows[:, :, None] & cols[:, None, :])[:, None]


def unaries_from_probs(probs: torch.Tensor, blur: int) -> torch.Tensor:
    """(B, 15, gh, gw) class probabilities -> (B, 14, gh, gw) log-prob unaries (blurred)."""
    return torch.log(box_mean(probs[:, :NUM_JOINTS], blur) + LOG_EPS)


@dataclass
class Estimate2D:
    """Result of PoseEstimator2D.estimate for B images.

    joints_2d: (B, 14, 2) float32, pixels of the input image.
    joint_scores: (B, 14) float32, each joint's unary log-probability at its MAP cell (before
        joint_cells moved it; PsmResult.joint_scores).
    score: (B,) float32, the PSM score of the chosen scale.
    unaries: (B, 14, h, w) float32 log-probabilities of the chosen scale, padded to a common
        (h, w) with log(LOG_EPS).
    map_to_image: (B, 2, 3) float32 affine map from unary cell (u = column, v = row, 1) to image
        pixels (x, y): image_xy = map_to_image @ (u, v, 1).
    scale: (B,) float32, the working scale chosen (working px per image px, mean of x and y).
    facing_camera: (B,) float32, the probability that the person faces the camera: with a joint
        network, the sigmoid of the PSM score of the cascade's labelling minus that of the
        swapped one (left_right_hypotheses); else the facing model's (1 for models with
        neither); below 0.5, left and right were swapped.
    timings: seconds per step (features, traversal, jointnet, psm, total).
    """

    joints_2d: torch.Tensor
    joint_scores: torch.Tensor
    score: torch.Tensor
    unaries: torch.Tensor
    map_to_image: torch.Tensor
    scale: torch.Tensor
    facing_camera: torch.Tensor
    timings: dict[str, float] = field(default_factory=dict)

    def sample_unaries(self, points: torch.Tensor) -> torch.Tensor:
        """Unary log-probs at image points, bilinear on the unary grid.

        points: (B, K, 14, 2) float32 image pixels -> (B, K, 14) float32; points outside the
        map get log(LOG_EPS).
        """
        b, k = points.shape[:2]
        a = self.map_to_image[:, :, :2]  # (B, 2, 2), diagonal
        t = self.map_to_image[:, :, 2]  # (B, 2)
        uv = (points - t[:, None, None, :]) / torch.diagonal(a, dim1=1, dim2=2)[:, None, None, :]
        h, w = self.unaries.shape[-2:]
        # grid_sample wants (x, y) in [-1, 1] with align_corners=True: -1 = cell 0.
        norm = torch.stack([uv[..., 0] / max(w - 1, 1), uv[..., 1] / max(h - 1, 1)], -1) * 2 - 1
        # One sampling grid per joint: treat joints as the batch of (1-channel) maps.
        maps = self.unaries.reshape(b * NUM_JOINTS, 1, h, w)
        grid = norm.permute(0, 2, 1, 3).reshape(b * NUM_JOINTS, k, 1, 2)
        out = torch.nn.functional.grid_sample(
            maps - np.log(LOG_EPS), grid, mode="bilinear", padding_mode="zeros", align_corners=True
        )  # shifted so that outside (zero padding) means log(LOG_EPS)
        return (out.reshape(b, NUM_JOINTS, k).permute(0, 2, 1) + np.log(LOG_EPS)).contiguous()


def save_forest(forest: Forest, path: Path) -> None:
    """Write a forest gzip-compressed (the tensors shrink ~2.5x, a 16-tree layer from 16 to 6 MB);
    the header's time is fixed so that the same forest always gives the same bytes."""
    with open(path, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as out:
        torch.save(forest.to_dict(), out)


def load_forest(path: Path) -> Forest:
    """A forest written by save_forest."""
    try:
        with gzip.open(path, "rb") as f:
            data = io.BytesIO(f.read())  # torch.load wants a seekable file
        return Forest.from_dict(torch.load(data, weights_only=True))
    except (OSError, EOFError, KeyError, RuntimeError) as exc:
        raise DataFormatError(f"cannot load forest {path}: {exc}") from exc


def load_facing(path: Path) -> FacingNet:
    """The facing CNN's saved state dict (ds3d.image2d.facing) -> the network, in eval mode."""
    net = FacingNet()
    net.load_state_dict(torch.load(path, weights_only=True))
    return net.eval()


def load_jointnet(path: Path) -> JointNet:
    """The joint network's saved state dict (ds3d.image2d.jointnet) -> the network, eval mode."""
    net = JointNet()
    net.load_state_dict(torch.load(path, weights_only=True))
    return net.eval()


def read_manifest(model_dir: Path) -> dict:
    path = Path(model_dir) / "manifest.json"
    if not path.is_file():
        raise DataFormatError(f"no manifest.json in {model_dir}")
    return json.loads(path.read_text())


@dataclass
class _Crop:
    """Where one image's working region comes from: its top-left corner (x0, y0) in image px
    and the base scale (working px per image px)."""

    image: np.ndarray
    x0: int
    y0: int
    base: float


def _crops(images: list[np.ndarray], bboxes, params: EstimatorParams) -> list[_Crop]:
    """Base scale per image: from the person box if given, else from the image size."""
    out = []
    for i, image in enumerate(images):
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InvalidImage(
                f"image {i} must be (H, W, 3) uint8, got {image.shape} {image.dtype}"
            )
        box = None if bboxes is None else bboxes[i]
        if box is None:
            extent = max(image.shape[:2]) / params.image_to_extent
            out.append(_Crop(image, 0, 0, params.canonical_extent / extent))
            continue
        x0, y0, x1, y1 = (float(v) for v in box)
        if not (np.isfinite([x0, y0, x1, y1]).all() and x1 > x0 and y1 > y0):
            raise ValueError(f"bbox {i} must be finite (x0, y0, x1, y1) with x1 > x0, y1 > y0")
        extent = max(x1 - x0, y1 - y0) / params.box_to_extent
        margin = params.box_margin * extent
        h, w = image.shape[:2]
        cx0, cy0 = max(int(x0 - margin), 0), max(int(y0 - margin), 0)
        cx1, cy1 = min(int(np.ceil(x1 + margin)), w), min(int(np.ceil(y1 + margin)), h)
        if cx1 <= cx0 or cy1 <= cy0:
            raise ValueError(f"bbox {i} lies outside its image")
        crop = np.ascontiguousarray(image[cy0:cy1, cx0:cx1])
        out.append(_Crop(crop, cx0, cy0, params.canonical_extent / extent))
    return out


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
    ):
        if params.observer_labels and facing is None and jointnet is None and layers:
            raise DataFormatError("observer-centric labels need a facing model or joint network")
        self.layers = layers
        self.mixtures = mixtures
        self.params = params
        self.facing = facing
        self.jointnet = jointnet
        self._first_trees: dict[int, list[Forest]] = {}  # coarse-pass layers, per tree count

    @classmethod
    def load(cls, model_dir: Path | str | None = None) -> PoseEstimator2D:
        model_dir = Path(model_dir) if model_dir is not None else MODELS_DIR / "image2d"
        manifest = read_manifest(model_dir)
        try:
            params = EstimatorParams(**manifest["params"])
            layers = [load_forest(model_dir / name) for name in manifest["layers"]]
            state = torch.load(model_dir / manifest["psm"], weights_only=True)
            mixtures = PairwiseMixtures.from_state_dict(state)
            facing = manifest.get("facing")
            facing = load_facing(model_dir / facing) if facing else None
            jointnet = manifest.get("jointnet")
            jointnet = load_jointnet(model_dir / jointnet) if jointnet else None
        except (KeyError, TypeError, OSError, RuntimeError) as exc:
            raise DataFormatError(f"bad 2D model in {model_dir}: {exc}") from exc
        return cls(layers, mixtures, params, facing, jointnet)

    def _facing(
        self, channels: torch.Tensor, joints: torch.Tensor, sizes: list[tuple[int, int]]
    ) -> torch.Tensor:
        """P(faces the camera) from the facing model around the PSM's pose
        (ds3d.image2d.facing). channels: (B, 12, H, W), zero-padded; joints: (B, 14, 2) (x, y)
        px on them; sizes: B (h, w) -> (B,) float32 (1 for a model without a facing model)."""
        if self.facing is None:
            return torch.ones(channels.shape[0])
        return faces_camera_probability(self.facing, channels[:, :3], joints, sizes)

    def _jointnet_unaries(
        self, channels: torch.Tensor, sizes: list[tuple[int, int]], stride: int
    ) -> torch.Tensor:
        """The joint network's unaries on the grid: channels (b, 12, H, W) zero-padded, sizes b
        (h, w) -> (b, 14, gh, gw) log(P(joint at the cell) + LOG_EPS), floored as the forests'
        unaries are; log(LOG_EPS) outside each image. Each image runs alone on its own pixels:
        past the first batch norm, a padded batch's zeros are no longer zeros, and the network
        sees about 300 px around each cell."""
        h, w = channels.shape[-2:]
        out = torch.full((len(sizes), NUM_JOINTS, -(-h // stride), -(-w // stride)), LOG_EPS)
        for i, (hi, wi) in enumerate(sizes):
            logits = logits_on_grid(self.jointnet, channels[i : i + 1, :3, :hi, :wi], stride)
            out[i, :, : logits.shape[2], : logits.shape[3]] = spatial_softmax(logits)[0] + LOG_EPS
        return out.log()

    def scales(self) -> list[float]:
        p = self.params
        return [p.scale_start * p.scale_factor**k for k in range(p.n_scales)]

    def estimate(
        self,
        images: list[np.ndarray],
        bboxes: list | None = None,
        scales: list[float] | None = None,
    ) -> Estimate2D:
        """2D poses of a batch of images.

        images: B arrays (H_i, W_i, 3) uint8 RGB; bboxes: None or B entries, each None or a
        person box (x0, y0, x1, y1) in image pixels (the region around it is cropped first).
        scales: pyramid scales relative to the base scale (default: the model's 6).
        Returns Estimate2D (joints in each input image's pixels).

        With `select_stride`, a coarse pass (that stride) over every scale picks each image's
        scale by its PSM score, and only the chosen scale is run at `stride`; otherwise every
        scale runs at `stride` and the best PSM score wins.

        With torch.get_num_threads() = N > 1, the batch is split into N parts run at once on N
        threads of one intra-op thread each: the traversal's gathers do not parallelise within
        an op, but whole images do (2 threads: 1.6-1.9x at batch 16, docs/RESULTS.md;
        ds3d.threads). Each image's result does not depend on the batch it is in, so neither
        does it on N. The step timings are then summed over the threads (CPU seconds); "total"
        is wall-clock.
        """
        if len(images) == 0:
            raise ValueError("no images")
        if bboxes is not None and len(bboxes) != len(images):
            raise ValueError(f"{len(bboxes)} bboxes for {len(images)} images")
        t_start = now()
        crops = _crops(images, bboxes, self.params)
        scales = list(scales) if scales is not None else self.scales()
        parts = split_rows(len(crops))
        results = map_on_threads(
            lambda rows: self._estimate_crops([crops[i] for i in rows], scales), parts
        )
        if len(parts) == 1:
            best = results[0]
        else:
            best = _gather_rows(list(zip(parts, results, strict=True)), len(crops))
            best.timings = {k: sum(r.timings[k] for r in results) for k in results[0].timings}
        timings = {k: round(v, 6) for k, v in best.timings.items()}
        best = _person_centric(best)
        best.timings = {**timings, "total": round(now() - t_start, 6)}
        return best

    def _estimate_crops(self, crops: list[_Crop], scales: list[float]) -> Estimate2D:
        """estimate() of crops on the calling thread, before the left/right decision; sets
        timings of the steps (seconds)."""
        p = self.params
        timings = {"features": 0.0, "traversal": 0.0, "jointnet": 0.0, "psm": 0.0}
        if p.select_stride is None or len(scales) == 1:
            best = None
            for rel in scales:
                cand = self._one_scale(crops, rel, self.layers, p, timings)
                best = cand if best is None else _keep_better(best, cand)
        else:
            # The coarse pass blurs its unaries over the same pixels (at least one cell).
            coarse = replace(
                p,
                stride=p.select_stride,
                unary_blur=max(1, round(p.unary_blur * p.stride / p.select_stride)),
                flip_test=False,
            )
            layers = self.layers if p.coarse_trees is None else self._coarse_layers(p.coarse_trees)
            score = torch.stack(
                [
                    self._one_scale(crops, rel, layers, coarse, timings, final=False).score
                    for rel in scales
                ]
            )
            choice = score.argmax(dim=0)  # (B,) index into scales
            parts = []
            for k in choice.unique().tolist():
                rows = torch.nonzero(choice == k).view(-1)
                part = self._one_scale([crops[i] for i in rows], scales[k], self.layers, p, timings)
                parts.append((rows, part))
            best = _gather_rows(parts, len(crops))
        best.timings = timings
        return best

    def _coarse_layers(self, k: int) -> list[Forest]:
        """The layers cut to their first k trees, made once per k (a new Forest converts its
        node reads again, Forest.node_reads)."""
        if k not in self._first_trees:
            self._first_trees[k] = [forest.first_trees(k) for forest in self.layers]
        return self._first_trees[k]

    def _one_scale(
        self,
        crops: list[_Crop],
        rel: float,
        layers: list[Forest],
        p: EstimatorParams,
        timings: dict[str, float],
        final: bool = True,
    ) -> Estimate2D:
        """Cascade (`layers`) + PSM of every crop at `rel` times its base scale, with params p
        (whose stride and blur may differ from the model's); adds the seconds of each step to
        timings. final: whether this pass answers, so runs the joint network (its unaries are
        added to the cascade's, left_right_hypotheses) or else the facing model (the coarse
        pass only needs the cascade's scores; its facing_camera is then 1). The cascade runs on
        groups of images of similar shape (_traversal_groups), the PSM on the whole batch at
        once."""
        t0 = now()
        resized = [resize_image(c.image, c.base * rel) for c in crops]
        sizes = [r.shape[:2] for r in resized]
        timings["features"] += now() - t0
        parts = [
            _group_unaries(resized, rows, layers, self.mixtures, p, timings)
            for rows in _traversal_groups(sizes, layers[-1])
        ]
        # Back to the batch's order, padded to one grid (log(LOG_EPS) outside each image).
        gh = max(u.shape[2] for _, _, u in parts)
        gw = max(u.shape[3] for _, _, u in parts)
        unaries = torch.empty(len(crops), NUM_JOINTS, gh, gw)
        for rows, _, u in parts:
            unaries[rows] = _pad_maps(u, gh, gw)
        with_net = final and self.jointnet is not None and p.jointnet_weight > 0
        if with_net:
            t1 = now()
            net = torch.empty_like(unaries)
            for rows, channels, _ in parts:
                maps = self._jointnet_unaries(channels, [sizes[i] for i in rows.tolist()], p.stride)
                net[rows] = _pad_maps(maps, gh, gw)
            timings["jointnet"] += now() - t1
        t1 = now()
        faces = torch.ones(len(crops))
        if with_net:  # the joint network's maps settle left and right
            unaries, res, faces = left_right_hypotheses(unaries, net, self.mixtures, p)
            # The centroid sharpens the sum of the two, as the PSM weighs them.
            working = p.joint_cells(unaries * (1 + p.jointnet_weight), res.cells) * p.stride
        else:
            res = infer(unaries * p.unary_weight, self.mixtures, stride=float(p.stride))
            res = replace(res, joint_scores=res.joint_scores / p.unary_weight)  # log-probs
            working = p.joint_cells(unaries, res.cells) * p.stride  # (B, 14, 2) px, working
            if final:
                for rows, channels, _ in parts:
                    faces[rows] = self._facing(
                        channels, working[rows], [sizes[i] for i in rows.tolist()]
                    )
        timings["psm"] += now() - t1
        fac = torch.tensor(
            [
                [r.shape[1] / c.image.shape[1], r.shape[0] / c.image.shape[0]]
                for r, c in zip(resized, crops, strict=True)
            ],
            dtype=torch.float32,
        )  # (B, 2) working px per image px, (x, y)
        off = torch.tensor([[c.x0, c.y0] for c in crops], dtype=torch.float32)
        joints = (working + 0.5) / fac[:, None] - 0.5 + off[:, None]
        affine = torch.zeros(len(crops), 2, 3)
        affine[:, 0, 0] = p.stride / fac[:, 0]
        affine[:, 1, 1] = p.stride / fac[:, 1]
        affine[:, :, 2] = 0.5 / fac - 0.5 + off
        return Estimate2D(
            joints,
            res.joint_scores.float(),
            res.score.float(),
            unaries,
            affine,
            fac.mean(1),
            faces,
        )


def left_right_hypotheses(
    forest: torch.Tensor, net: torch.Tensor, mixtures: PairwiseMixtures, p: EstimatorParams
) -> tuple[torch.Tensor, PsmResult, torch.Tensor]:
    """The PSM on the forests' unaries plus jointnet_weight times the joint network's, with the
    forests' maps taken as they are and with their left and right swapped: the forests label
    the limb on the image's left "right" (as if everyone faced the camera), the network labels
    the person's own, so the better score of the two says whether the person faces the camera.

    forest, net: (B, 14, H, W) log-probability unaries -> (unaries (B, 14, H, W), the PSM's
    result, (B,) P(faces the camera)): the chosen labelling's unaries as a weighted mean,
    (forest + w net) / (1 + w), so that they stay log-probabilities floored at log(LOG_EPS)
    like the forests' (the PSM weighs them by unary_weight * (1 + w): it sees the sum), and
    its MAP pose, both in the forests' labelling (so that _person_centric swaps them to the
    person's own where P < 0.5); P is the sigmoid of the score difference of the two
    labellings."""
    b, flip, w = len(forest), list(FLIP), p.jointnet_weight
    both = (torch.cat([forest, forest[:, flip]]) + w * net.repeat(2, 1, 1, 1)) / (1 + w)
    res = infer(both * (p.unary_weight * (1 + w)), mixtures, stride=float(p.stride))
    facing = torch.sigmoid(res.score[:b] - res.score[b:])
    away = facing < 0.5
    rows = torch.arange(b) + b * away.long()

    def forest_labels(t: torch.Tensor) -> torch.Tensor:
        """Rows of the chosen labelling, joints back in the forests' order."""
        t = t[rows]
        return torch.where(away.view(-1, *[1] * (t.ndim - 1)), t[:, flip], t)

    chosen = PsmResult(
        forest_labels(res.joints_2d),
        forest_labels(res.cells),
        res.score[rows],
        forest_labels(res.joint_scores) / (p.unary_weight * (1 + w)),
    )
    return forest_labels(both), chosen, facing


def _group_unaries(
    images: list[np.ndarray],
    rows: list[int],
    layers: list[Forest],
    mixtures: PairwiseMixtures,
    p: EstimatorParams,
    timings: dict[str, float],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The cascade's unaries of the images[rows] (H_i, W_i, 3) uint8, zero-padded into one batch;
    with `p.flip_test`, the last layer's probabilities are averaged with those of each image's
    mirror (mirror_on_grid), mapped back.

    Returns (rows (b,) long, channels (b, 12, H, W) float32, unaries (b, 14, gh, gw) float32
    log-probabilities on the grid of grid_positions(H, W, p.stride), log(LOG_EPS) outside each
    image), H x W the group's largest height and width; adds the seconds of the features and of
    the traversal to timings."""
    group = [images[i] for i in rows]
    sizes = [image.shape[:2] for image in group]
    channels, probs = _group_probs(group, layers, mixtures, p, timings)
    if p.flip_test:
        mirrors = [mirror_on_grid(image, p.stride) for image in group]
        mirrored = _group_probs(mirrors, layers, mixtures, p, timings)[1]
        probs = (probs + _unmirror(mirrored, sizes, p.stride, probs.shape)) / 2
    unaries = unaries_from_probs(probs, p.unary_blur)  # zero outside each image
    valid = valid_cells(sizes, channels.shape[2], channels.shape[3], p.stride)  # (b, 1, gh, gw)
    unaries = torch.where(valid, unaries, torch.full_like(unaries, np.log(LOG_EPS)))
    return torch.tensor(rows), channels, unaries


def _group_probs(
    group: list[np.ndarray],
    layers: list[Forest],
    mixtures: PairwiseMixtures,
    p: EstimatorParams,
    timings: dict[str, float],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Images (H_i, W_i, 3) uint8 zero-padded into one batch -> their channels (b, 12, H, W)
    and the last layer's probabilities (b, 15, gh, gw) (mixtures: the PSM's, for
    layer_context); adds the seconds of the features and of the traversal to timings."""
    t0 = now()
    sizes = [image.shape[:2] for image in group]
    channels = _batch_channels(group, max(h for h, _ in sizes), max(w for _, w in sizes))
    t1 = now()
    probs = cascade_probs(layers, channels, p, sizes, mixtures)[-1]
    timings["features"] += t1 - t0
    timings["traversal"] += now() - t1
    return channels, probs


def mirror_on_grid(image: np.ndarray, stride: int) -> np.ndarray:
    """(H, W, 3) -> the image mirrored left-right, less its first (W - 1) % stride columns, so
    that the grid of grid_positions on it is the image's own grid mirrored: column j of that
    grid lands on column (W - 1) // stride - j of the image's."""
    return np.ascontiguousarray(image[:, ::-1][:, (image.shape[1] - 1) % stride :])


def _unmirror(
    probs: torch.Tensor, sizes: list[tuple[int, int]], stride: int, shape: torch.Size
) -> torch.Tensor:
    """Class probabilities (b, 15, gh', gw') of the images' mirror_on_grid -> on the images' own
    grids (b, 15, gh, gw) = shape: columns reversed, left and right swapped (background kept),
    zero outside each image; sizes: the b images' (h, w)."""
    out = torch.zeros(shape)
    classes = [*FLIP, NUM_JOINTS]
    for k, (h, w) in enumerate(sizes):
        gh, gw = -(-h // stride), -(-w // stride)
        out[k, :, :gh, :gw] = probs[k, classes, :gh, :gw].flip(-1)
    return out


# Bytes of a traversal group's padded channel stack (pad_channels). Larger buffers are mmapped
# afresh by malloc on every call and page-faulted in: a batch of 16 LSP images run as one group
# was 1.2x slower than 4 at a time (docs/RESULTS.md).
GROUP_BYTES = 16 * 2**20


def _traversal_groups(sizes: list[tuple[int, int]], last_layer: Forest) -> list[list[int]]:
    """Rows of a batch of images (h, w) in groups run through the cascade together: images of
    similar shape (sorted by aspect ratio, so little of a group is padding), each group's padded
    stack of `last_layer`'s channels within GROUP_BYTES (at least one image per group)."""
    pad = 2 * last_layer.radius
    per_px = 4 * (last_layer.n_channels + 1)  # float32 bytes per padded pixel
    groups: list[list[int]] = []
    hmax = wmax = 0
    for i in sorted(range(len(sizes)), key=lambda i: (sizes[i][0] / sizes[i][1], i)):
        h, w = max(hmax, sizes[i][0]), max(wmax, sizes[i][1])
        if groups and (len(groups[-1]) + 1) * per_px * (h + pad) * (w + pad) <= GROUP_BYTES:
            groups[-1].append(i)
            hmax, wmax = h, w
        else:
            groups.append([i])
            hmax, wmax = sizes[i]
    return groups


def _batch_channels(images: list[np.ndarray], height: int, width: int) -> torch.Tensor:
    """Channels per image, zero-padded into a (B, 12, height, width) batch: exactly what a
    single image sees in training (zero outside the image), whatever the batch."""
    out = torch.zeros(len(images), NUM_IMAGE_CHANNELS, height, width)
    for i, r in enumerate(images):
        out[i, :, : r.shape[0], : r.shape[1]] = image_channels(torch.from_numpy(r)[None])[0]
    return out


def _person_centric(est: Estimate2D) -> Estimate2D:
    """Swap left and right of the images whose person faces away (observer -> person labels)."""
    away = est.facing_camera < 0.5
    flip = list(FLIP)
    return Estimate2D(
        torch.where(away.view(-1, 1, 1), est.joints_2d[:, flip], est.joints_2d),
        torch.where(away.view(-1, 1), est.joint_scores[:, flip], est.joint_scores),
        est.score,
        torch.where(away.view(-1, 1, 1, 1), est.unaries[:, flip], est.unaries),
        est.map_to_image,
        est.scale,
        est.facing_camera,
    )


def _pad_maps(maps: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Pad (B, 14, h0, w0) log-prob maps to (B, 14, h, w) with log(LOG_EPS)."""
    out = torch.full((*maps.shape[:2], h, w), float(np.log(LOG_EPS)), dtype=maps.dtype)
    out[:, :, : maps.shape[2], : maps.shape[3]] = maps
    return out


def _keep_better(a: Estimate2D, b: Estimate2D) -> Estimate2D:
    """Per image, the estimate with the higher PSM score."""
    take_b = b.score > a.score
    h = max(a.unaries.shape[2], b.unaries.shape[2])
    w = max(a.unaries.shape[3], b.unaries.shape[3])
    sel = take_b.view(-1, 1, 1, 1)
    return Estimate2D(
        torch.where(take_b.view(-1, 1, 1), b.joints_2d, a.joints_2d),
        torch.where(take_b.view(-1, 1), b.joint_scores, a.joint_scores),
        torch.where(take_b, b.score, a.score),
        torch.where(sel, _pad_maps(b.unaries, h, w), _pad_maps(a.unaries, h, w)),
        torch.where(take_b.view(-1, 1, 1), b.map_to_image, a.map_to_image),
        torch.where(take_b, b.scale, a.scale),
        torch.where(take_b, b.facing_camera, a.facing_camera),
    )


def _gather_rows(parts: list[tuple[torch.Tensor, Estimate2D]], b: int) -> Estimate2D:
    """One Estimate2D of b images from parts that each hold some of them: (rows (n,) long,
    the estimate of those n images). Unary maps are padded to a common size."""
    h = max(part.unaries.shape[2] for _, part in parts)
    w = max(part.unaries.shape[3] for _, part in parts)
    rows = torch.cat([r for r, _ in parts])
    order = torch.empty_like(rows)
    order[rows] = torch.arange(b)  # where each image's row lies in the concatenation

    def cat(get):
        return torch.cat([get(part) for _, part in parts])[order]

    return Estimate2D(
        cat(lambda e: e.joints_2d),
        cat(lambda e: e.joint_scores),
        cat(lambda e: e.score),
        cat(lambda e: _pad_maps(e.unaries, h, w)),
        cat(lambda e: e.map_to_image),
        cat(lambda e: e.scale),
        cat(lambda e: e.facing_camera),
    )


def now() -> float:
    return time.perf_counter()
