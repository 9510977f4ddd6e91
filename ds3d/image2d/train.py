"""Training of the 2D stage: a forest cascade, the PSM's pairwise mixtures and a network, the
joint network (ds3d.image2d.jointnet, a second unary) or, for a model without one, a facing
model.

Data: LSP train (im0001-im1000, minus the last `n_val` images, held out for validation) and
LSPet (10,000). Every image is rescaled so that its person spans `canonical_extent` px
(estimator.EstimatorParams). The images are split into one share per cascade layer: layer 1
grows on the first; each later layer grows on its own share, reading the maps of the layers
before it computed on images they never saw, so that its context features see maps as noisy as
at test time (stacking without leakage).

The joint network (jointnet_windows, ds3d.image2d.jointnet_train) learns person-centric labels
from the whole person, and so which arm is the right one. Without it, whether the person faces
the camera (then person-centric = observer-centric labels) or away (then left and right swap)
is learnt by a small CNN on the image around the torso (ds3d.image2d.facing, train_facing).
Labels can be observer-centric
outright (`EstimatorParams.observer_labels`): in every training image the arm whose shoulder is
on the image's left is called "right", and likewise the leg by its hip, which is what local
image evidence can tell.

Each tree draws its own images (random horizontal flips), its own pixels (positives near the
visible joints, background elsewhere) and its own pool of random pixel comparisons, and is
grown by scikit-learn (ds3d.image2d.forest).
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ds3d.data.lsp import PoseAnnotations, load_lsp, load_lspet
from ds3d.image2d import jointnet_train
from ds3d.image2d.estimator import (
    EstimatorParams,
    cascade_probs,
    context_channels,
    layer_context,
    resize_image,
    save_forest,
)
from ds3d.image2d.facing import FacingNet, crop, crop_centre, observer_order
from ds3d.image2d.features import (
    NUM_IMAGE_CHANNELS,
    evaluate_pool,
    image_channels,
    lab_channels,
    pad_channels,
    sample_pool,
)
from ds3d.image2d.forest import Forest, fit_tree, stack_trees
from ds3d.image2d.psm import PairwiseMixtures, fit_pairwise_mixtures
from ds3d.image_io import read_image
from ds3d.skeleton import FLIP, L_HIP, L_SHOULDER, NECK, NUM_JOINTS, R_HIP, R_SHOULDER

log = logging.getLogger(__name__)

BACKGROUND = NUM_JOINTS  # class id of background pixels
NET_FILES = {"facing": "facing.pt", "jointnet": "jointnet.pt"}


@dataclass
class TrainConfig:
    """What `ds3d train-2d` trains; the defaults are the full model."""

    seed: int = 0
    n_val: int = 300  # last LSP train images held out for validation
    max_images: int | None = None  # cap on training images (small mode)
    trees: tuple[int, ...] = (16, 16)  # trees per cascade layer
    images_per_tree: int = 4000  # of the ~5,350 in a layer's share; 2000 measured 2.5 points worse
    pool_size: int = 512  # random comparisons offered to each tree
    radius: int = 40  # max offset of a comparison, px at the working scale
    pos_per_joint: int = 8
    pos_radius: float = 5.0  # px: pixels this close to a joint are that joint's positives
    facing_epochs: int = 48  # of the facing CNN (ds3d.image2d.facing)
    facing_lr: float = 3e-3  # its peak learning rate (one cycle)
    jointnet_epochs: int = 14  # of the joint network (ds3d.image2d.jointnet); 0: facing CNN
    jointnet_lr: float = 3e-3  # its peak learning rate (one cycle)
    bg_per_image: int = 64
    max_depth: int = 20
    min_samples_leaf: int = 20
    # The paper has 15; on the 300 held-out images 3 scored best (C = 1 / 3 / 5 / 8 / 15: 38.2 /
    # 40.2 / 39.2 / 38.2 / 39.0 % PCK@0.2), within the noise of 15 and with a 5x cheaper PSM.
    psm_components: int = 3
    psm_iterations: int = 50


@dataclass
class TrainingImage:
    """One image at the working scale. image: (H, W, 3) uint8; joints: (14, 2) px;
    visible: (14,) bool."""

    image: np.ndarray
    joints: np.ndarray
    visible: np.ndarray


def person_extent(joints: np.ndarray, visible: np.ndarray) -> float:
    """Longer side of the box around the visible joints (all joints if < 2 visible), px."""
    pts = joints[visible] if visible.sum() >= 2 else joints
    return float(max((pts.max(0) - pts.min(0)).max(), 1.0))


def working_scale_joints(joints: np.ndarray, visible: np.ndarray, extent: float) -> np.ndarray:
    """Scale factors that bring each person to the canonical extent. (N, 14, 2) -> (N,)."""
    return np.array([extent / person_extent(j, v) for j, v in zip(joints, visible, strict=True)])


def load_training_image(
    ann: PoseAnnotations, index: int, flip: bool, params: EstimatorParams
) -> TrainingImage:
    joints = ann.joints[index].astype(np.float32)
    visible = ann.visible[index].copy()
    scale = params.canonical_extent / person_extent(joints, visible)
    raw = read_image(ann.image_paths[index])
    image = resize_image(raw, scale)
    # Exact per-axis factors of the rounded output size; pixel centres map as x' = (x+.5)s-.5.
    sy, sx = image.shape[0] / raw.shape[0], image.shape[1] / raw.shape[1]
    joints = (joints + 0.5) * np.array([sx, sy], dtype=np.float32) - 0.5
    if flip:
        image = np.ascontiguousarray(image[:, ::-1])
        joints[:, 0] = image.shape[1] - 1 - joints[:, 0]
        joints, visible = joints[list(FLIP)], visible[list(FLIP)]
    return TrainingImage(image, joints, visible)


def faces_camera(joints: np.ndarray) -> bool:
    """Person-centric (14, 2) joints: True when the right shoulder is left of the left one."""
    return bool(joints[R_SHOULDER, 0] < joints[L_SHOULDER, 0])


def observer_centric(joints: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relabel (14, 2) joints / (14,) visibility so that the arm (leg) whose shoulder (hip) is
    on the image's left is the right one."""
    order = observer_order(torch.from_numpy(joints)[None])[0].numpy()
    return joints[order], visible[order]


def sample_pixels(
    rng: np.random.Generator, sample: TrainingImage, cfg: TrainConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Training pixels of one image: (P, 2) int64 (y, x) and (P,) int64 labels (joint or 14).

    Positives: pos_per_joint pixels uniform in a disc of pos_radius around each visible joint.
    Background: bg_per_image uniform pixels farther than 1.5 pos_radius from every joint.
    """
    h, w = sample.image.shape[:2]
    pos, lab = [], []
    for j in np.flatnonzero(sample.visible):
        angle = rng.random(cfg.pos_per_joint) * 2 * np.pi
        r = np.sqrt(rng.random(cfg.pos_per_joint)) * cfg.pos_radius
        y = np.round(sample.joints[j, 1] + r * np.sin(angle)).astype(np.int64)
        x = np.round(sample.joints[j, 0] + r * np.cos(angle)).astype(np.int64)
        ok = (y >= 0) & (y < h) & (x >= 0) & (x < w)
        pos.append(np.stack([y[ok], x[ok]], 1))
        lab.append(np.full(ok.sum(), j))
    bg = np.stack([rng.integers(0, h, cfg.bg_per_image), rng.integers(0, w, cfg.bg_per_image)], 1)
    # Occluded LSP joints are real positions: keep background away from every joint.
    d = np.linalg.norm(bg[:, None, ::-1] - sample.joints[None], axis=-1)
    far = d.min(1) > 1.5 * cfg.pos_radius
    pos.append(bg[far])
    lab.append(np.full(far.sum(), BACKGROUND))
    return np.concatenate(pos).astype(np.int64), np.concatenate(lab).astype(np.int64)


def stacked_channels(
    sample: TrainingImage, context: torch.Tensor | None, params: EstimatorParams
) -> torch.Tensor:
    """(1, C, H, W) channels the layer reads: image channels, plus the context if given
    (context: (1, C_ctx, gh, gw) layer_context of the layers before, on the stride grid)."""
    ch = image_channels(torch.from_numpy(sample.image)[None])
    if context is None:
        return ch
    h, w = sample.image.shape[:2]
    return torch.cat([ch, context_channels(context.float(), params.stride, h, w)], dim=1)


def grow_layer(
    ann: PoseAnnotations,
    items: list[tuple[int, bool]],
    contexts: dict[tuple[int, bool], torch.Tensor] | None,
    n_trees: int,
    cfg: TrainConfig,
    params: EstimatorParams,
    rng: np.random.Generator,
) -> Forest:
    """Grow one cascade layer. items: (annotation index, flipped) pairs the layer may use;
    contexts: cascade_contexts per item for a context layer, None for layer 1."""
    n_ctx = 0 if contexts is None else next(iter(contexts.values())).shape[1]
    trees = []
    for t in range(n_trees):
        t0 = time.perf_counter()
        pool = sample_pool(rng, cfg.pool_size, cfg.radius, NUM_IMAGE_CHANNELS, n_ctx)
        chosen = rng.choice(len(items), min(cfg.images_per_tree, len(items)), replace=False)
        xs, ys = [], []
        for k in chosen:
            index, flip = items[k]
            if contexts is None:
                flip = bool(rng.random() < 0.5)
            sample = load_training_image(ann, index, flip, params)
            if params.observer_labels:
                sample = TrainingImage(
                    sample.image, *observer_centric(sample.joints, sample.visible)
                )
            ctx = contexts[items[k]] if contexts is not None else None
            padded = pad_channels(stacked_channels(sample, ctx, params), cfg.radius)[0]
            positions, labels = sample_pixels(rng, sample, cfg)
            xs.append(evaluate_pool(padded, cfg.radius, torch.from_numpy(positions), pool).numpy())
            ys.append(labels)
        t1 = time.perf_counter()
        tree = fit_tree(
            np.concatenate(xs),
            np.concatenate(ys),
            pool,
            NUM_JOINTS + 1,
            seed=int(rng.integers(2**31)),
            max_depth=cfg.max_depth,
            min_samples_leaf=cfg.min_samples_leaf,
        )
        trees.append(tree)
        log.info(
            "tree %d/%d: %d samples, %d nodes, depth %d, features %.1fs, fit %.1fs",
            t + 1,
            n_trees,
            sum(len(y) for y in ys),
            len(tree["left"]),
            tree["depth"],
            t1 - t0,
            time.perf_counter() - t1,
        )
    return stack_trees(trees, cfg.radius, NUM_IMAGE_CHANNELS + n_ctx)


FACING_MARGIN = 96  # px: a training window, from which the jittered CROP x CROP ones are cut
FACING_BATCH = 128


def facing_windows(ann: PoseAnnotations, params: EstimatorParams) -> tuple[Tensor, Tensor]:
    """The facing model's training data: for each image with both shoulders annotated, a
    FACING_MARGIN x FACING_MARGIN window of its Lab channels / 100 at the working scale (room for
    train_facing's jitter) around crop_centre of the annotated pose (where the neck or a hip is
    not annotated: 6 px below the shoulders' midpoint), and whether the person faces the camera
    (faces_camera). Returns ((N, 3, M, M) float16, (N,) float32)."""
    labelled = np.flatnonzero(ann.visible[:, [R_SHOULDER, L_SHOULDER]].all(1))
    windows = torch.empty(len(labelled), 3, FACING_MARGIN, FACING_MARGIN, dtype=torch.float16)
    labels = torch.empty(len(labelled))
    for k, i in enumerate(labelled):
        sample = load_training_image(ann, int(i), False, params)
        joints = torch.from_numpy(sample.joints)
        if sample.visible[[NECK, R_HIP, L_HIP]].all():
            centre = crop_centre(joints[None])
        else:
            shoulders = (joints[R_SHOULDER] + joints[L_SHOULDER]) / 2
            centre = (shoulders + torch.tensor([0.0, 6.0]))[None]
        lab = lab_channels(torch.from_numpy(sample.image)[None])
        windows[k] = crop(lab, centre, size=FACING_MARGIN)[0].half()
        labels[k] = float(faces_camera(sample.joints))
    return windows, labels


def jointnet_windows(ann: PoseAnnotations, params: EstimatorParams) -> tuple[Tensor, ...]:
    """The joint network's training data (ds3d.image2d.jointnet_train): per image, a window of
    WINDOW x WINDOW px of Lab / 100 at the working scale, centred on the box around its located
    joints; the joints in window px; which are located. Returns ((N, 3, WINDOW, WINDOW) float16,
    (N, 14, 2) float32 (x, y), (N, 14) bool)."""
    size = jointnet_train.WINDOW
    windows = torch.empty(len(ann), 3, size, size, dtype=torch.float16)
    joints = torch.empty(len(ann), NUM_JOINTS, 2)
    located = torch.from_numpy(ann.located.copy())
    for i in range(len(ann)):
        sample = load_training_image(ann, i, False, params)
        pts = torch.from_numpy(sample.joints)
        known = pts[located[i]] if located[i].sum() >= 2 else pts
        centre = ((known.min(0).values + known.max(0).values) / 2)[None]
        lab = lab_channels(torch.from_numpy(sample.image)[None])
        windows[i] = crop(lab, centre, size=size)[0].half()
        joints[i] = pts - centre + (size - 1) / 2
    return windows, joints, located


def train_facing(windows: Tensor, labels: Tensor, cfg: TrainConfig) -> FacingNet:
    """The facing model (ds3d.image2d.facing) trained on facing_windows: AdamW, a one-cycle
    learning rate peaking at `facing_lr`, `facing_epochs` epochs of batches of FACING_BATCH;
    every draw cuts a CROP window at a random scale (x0.87-1.15) and shift (+-8 px), mirrors
    it at random (facing the camera is mirror-invariant, so the label stays) and jitters its
    lightness and colour. The colour jitter and 48 epochs instead of 36 took the held-out ROC
    AUC at predicted poses from 0.805 to 0.847 (docs/RESULTS.md). Seeded by seed * 1000 + 7
    (torch's generator)."""
    torch.manual_seed(cfg.seed * 1000 + 7)
    net = FacingNet()
    opt = torch.optim.AdamW(net.parameters(), cfg.facing_lr, weight_decay=1e-3)
    steps = cfg.facing_epochs * -(-len(labels) // FACING_BATCH)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.facing_lr, total_steps=steps)
    middle = torch.full((1, 2), (FACING_MARGIN - 1) / 2)
    net.train()
    for epoch in range(cfg.facing_epochs):
        total = 0.0
        for rows in torch.randperm(len(labels)).split(FACING_BATCH):
            b = len(rows)
            shift = torch.empty(b, 2).uniform_(-8, 8)
            zoom = torch.empty(b).uniform_(0.87, 1.15)
            batch = crop(windows[rows].float(), middle + shift, zoom, torch.rand(b) < 0.5)
            batch[:, 0] += torch.empty(b, 1, 1).uniform_(-0.1, 0.1)  # lightness
            # Colour: clothes and backgrounds vary; a, b scaled and shifted per window.
            batch[:, 1:] = batch[:, 1:] * torch.empty(b, 1, 1, 1).uniform_(0.7, 1.3)
            batch[:, 1:] += torch.empty(b, 2, 1, 1).uniform_(-0.05, 0.05)
            loss = F.binary_cross_entropy_with_logits(net(batch), labels[rows])
            opt.zero_grad()
            loss.backward()
            opt.step()
            schedule.step()
            total += float(loss.detach()) * b
        log.info("facing epoch %d: loss %.4f", epoch + 1, total / len(labels))
    return net.eval()


def cascade_contexts(
    ann: PoseAnnotations,
    items: list[tuple[int, bool]],
    layers: list[Forest],
    params: EstimatorParams,
    mixtures: PairwiseMixtures,
) -> dict[tuple[int, bool], torch.Tensor]:
    """What the next layer reads of `layers` per item at the working scale: layer_context
    (1, C, gh, gw) float32 of the last layer's probabilities, rounded to float16 first (the
    layer 2 of the bundled model was grown on float16 maps; the rounding keeps it reproducible)."""
    out = {}
    for item in items:
        sample = load_training_image(ann, item[0], item[1], params)
        ch = image_channels(torch.from_numpy(sample.image)[None])
        probs = cascade_probs(layers, ch, params, mixtures=mixtures)[-1]
        out[item] = layer_context(probs.half().float(), params, mixtures)
    return out


def training_annotations(cfg: TrainConfig) -> tuple[PoseAnnotations, PoseAnnotations]:
    """(train, val): LSP train minus its last n_val images + LSPet; val = those n_val images."""
    lsp = load_lsp(split="train")
    n_fit = len(lsp) - cfg.n_val
    train = lsp.subset(range(n_fit)).concat(load_lspet())
    val = lsp.subset(range(n_fit, len(lsp)))
    if cfg.max_images is not None:
        keep = np.random.default_rng(cfg.seed).choice(len(train), cfg.max_images, replace=False)
        train = train.subset(np.sort(keep))
    return train, val


def psm_training_poses(ann: PoseAnnotations, params: EstimatorParams):
    """Training poses at the working scale (observer-centric if the model's labels are), with
    their mirror images: (2N, 14, 2) px, (2N, 14) bool."""
    scale = working_scale_joints(ann.joints, ann.visible, params.canonical_extent)
    joints = ann.joints * scale[:, None, None]
    visible = ann.visible
    if params.observer_labels:
        pairs = [observer_centric(j, v) for j, v in zip(joints, visible, strict=True)]
        joints = np.stack([j for j, _ in pairs])
        visible = np.stack([v for _, v in pairs])
    # A mirrored observer-centric pose is observer-centric again (x flips, and so do labels).
    mirrored = joints[:, list(FLIP)] * np.array([-1.0, 1.0], dtype=np.float32)
    visible = np.concatenate([visible, visible[:, list(FLIP)]])
    return np.concatenate([joints, mirrored]).astype(np.float32), visible


def fit_psm(ann: PoseAnnotations, cfg: TrainConfig, params: EstimatorParams) -> PairwiseMixtures:
    """The PSM's binaries from the training poses at the working scale (and their mirrors)."""
    joints, visible = psm_training_poses(ann, params)
    return fit_pairwise_mixtures(
        torch.from_numpy(joints)[None],
        visible=torch.from_numpy(visible)[None],
        n_components=cfg.psm_components,
        iterations=cfg.psm_iterations,
        seed=cfg.seed,
    )


def _grow_cascade(
    ann: PoseAnnotations,
    items: list[list[tuple[int, bool]]],
    cfg: TrainConfig,
    params: EstimatorParams,
    mixtures: PairwiseMixtures,
    rng: np.random.Generator,
) -> tuple[list[Forest], dict[str, float]]:
    """The cascade's layers, each on its share of the images (items: one list of (annotation
    index, flipped) per layer, see train; mixtures: the PSM's, for the contexts), and the
    seconds each took."""
    timings = {}
    layers: list[Forest] = []
    for depth, (n_trees, share) in enumerate(zip(cfg.trees, items, strict=True), 1):
        t0 = time.perf_counter()
        contexts = None
        if layers:
            contexts = cascade_contexts(ann, share, layers, params, mixtures)
            log.info(
                "layer-%d inputs of %d images: %.1fs", depth, len(share), time.perf_counter() - t0
            )
        layers.append(grow_layer(ann, share, contexts, n_trees, cfg, params, rng))
        timings[f"layer{depth}"] = time.perf_counter() - t0
    return layers, timings


def fit_facing(ann: PoseAnnotations, params: EstimatorParams, cfg: TrainConfig) -> dict:
    """The facing CNN's state dict, from facing_windows + train_facing."""
    return train_facing(*facing_windows(ann, params), cfg).state_dict()


def fit_jointnet(ann: PoseAnnotations, params: EstimatorParams, cfg: TrainConfig) -> dict:
    """The joint network's state dict, from jointnet_windows + jointnet_train.train_jointnet."""
    windows = jointnet_windows(ann, params)
    net = jointnet_train.train_jointnet(*windows, cfg.jointnet_epochs, cfg.jointnet_lr, cfg.seed)
    return net.state_dict()


def fit_on_one_thread(
    fit, ann: PoseAnnotations, params: EstimatorParams, cfg: TrainConfig, log_level: int
) -> tuple[dict[str, Tensor], float]:
    """fit_facing or fit_jointnet on one torch thread (train runs each in a worker process
    beside the forests): the state dict and the seconds it took. One thread, because the
    result depends on the thread count (the order in which gradients are summed)."""
    logging.basicConfig(level=log_level, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    return fit(ann, params, cfg), time.perf_counter() - t0


def train(cfg: TrainConfig, params: EstimatorParams, out_dir: Path, evaluate=None) -> dict:
    """Train the cascade, the PSM and one network (the joint network, or the facing CNN where
    cfg.jointnet_epochs is 0); write them with manifest.json to out_dir.

    evaluate: None or a callable(out_dir) -> dict of metrics, stored in the manifest.
    Returns the manifest dict.
    """
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    train_ann, _ = training_annotations(cfg)
    # One disjoint share of the images per layer: a context layer reads the maps of the layers
    # before it on images they never saw (stacking without leakage). Layer 1 draws a flip per
    # tree and image; later layers read precomputed maps, so each of their images has one flip.
    shares = np.array_split(rng.permutation(len(train_ann)), len(cfg.trees))
    items = [[(int(i), False) for i in shares[0]]] + [
        [(int(i), bool(rng.random() < 0.5)) for i in share] for share in shares[1:]
    ]
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    mixtures = fit_psm(train_ann, cfg, params)  # first: the cascade's contexts may run the PSM
    timings = {"psm": time.perf_counter() - t0}
    # The network needs nothing from the forests: it trains beside them in a process of its own
    # on one thread (scikit-learn grows a tree on one core), so that it is the same whatever
    # --threads says. The joint network settles left and right itself
    # (estimator.left_right_hypotheses); the facing CNN serves models without one.
    name, fit = ("jointnet", fit_jointnet) if cfg.jointnet_epochs else ("facing", fit_facing)
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=spawn) as pool:
        net = pool.submit(fit_on_one_thread, fit, train_ann, params, cfg, log.getEffectiveLevel())
        layers, layer_timings = _grow_cascade(train_ann, items, cfg, params, mixtures, rng)
        state, timings[name] = net.result()
    timings.update(layer_timings)
    layer_files = [f"forest{i + 1}.pt.gz" for i in range(len(layers))]
    for forest, layer_file in zip(layers, layer_files, strict=True):
        save_forest(forest, out_dir / layer_file)
    torch.save(state, out_dir / NET_FILES[name])
    torch.save(mixtures.state_dict(), out_dir / "psm.pt")
    timings["total"] = time.perf_counter() - t0
    manifest = {
        "model": "ds3d 2D pose: forest cascade unaries + pictorial structure model",
        "data": {
            "train": f"LSP train im0001-im{1000 - cfg.n_val:04d} + LSPet im00001-im10000"
            + (f", {cfg.max_images} of them drawn with the seed" if cfg.max_images else ""),
            "validation": f"LSP train im{1001 - cfg.n_val:04d}-im1000 (not trained on)",
            "n_train_images": len(train_ann),
            "terms": "LSP/LSPet: research use only (Johnson & Everingham, BMVC 2010, CVPR 2011)",
        },
        "seed": cfg.seed,
        "train_config": asdict(cfg),
        "params": asdict(params),
        "layers": layer_files,
        "psm": "psm.pt",
        "facing": NET_FILES["facing"] if name == "facing" else None,
        "jointnet": NET_FILES["jointnet"] if name == "jointnet" else None,
        "train_seconds": {k: round(v, 1) for k, v in timings.items()},
        "metrics": {},
    }
    write_manifest(out_dir, manifest)
    if evaluate is not None:
        manifest["metrics"]["validation"] = evaluate(out_dir)
        write_manifest(out_dir, manifest)
    return manifest


def write_manifest(out_dir: Path, manifest: dict) -> None:
    (Path(out_dir) / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
