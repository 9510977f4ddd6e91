"""The forest cascade's layers (ds3d.image2d.cascade), grown by scikit-learn.

The images are split into one share per cascade layer: layer 1 grows on the first; each later
layer grows on its own share, reading the maps of the layers before it computed on images they
never saw, so that its context features see maps as noisy as at test time (stacking without
leakage). Each tree draws its own images (random horizontal flips), its own pixels (positives
near the visible joints, background elsewhere) and its own pool of random pixel comparisons
(ds3d.image2d.forest).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from ds3d.data.lsp import PoseAnnotations
from ds3d.image2d.cascade import cascade_probs, context_channels, layer_context
from ds3d.image2d.features import (
    NUM_IMAGE_CHANNELS,
    evaluate_pool,
    image_channels,
    pad_channels,
    sample_pool,
)
from ds3d.image2d.forest import Forest
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures
from ds3d.skeleton import NUM_JOINTS
from ds3d.training.checkpoint import save_checkpoint
from ds3d.training.config import TrainConfig
from ds3d.training.images import TrainingImage, load_training_image, observer_centric
from ds3d.training.trees import fit_tree, stack_trees
from ds3d.util.progress import progress

log = logging.getLogger(__name__)

BACKGROUND = NUM_JOINTS  # class id of background pixels


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
    desc: str = "trees",
) -> Forest:
    """Grow one cascade layer. items: (annotation index, flipped) pairs the layer may use;
    contexts: cascade_contexts per item for a context layer, None for layer 1; desc: the
    progress bar's name."""
    n_ctx = 0 if contexts is None else next(iter(contexts.values())).shape[1]
    trees = []
    for t in progress(range(n_trees), desc=desc, unit="tree"):
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
    for item in progress(items, desc="layer inputs", unit="img"):
        sample = load_training_image(ann, item[0], item[1], params)
        ch = image_channels(torch.from_numpy(sample.image)[None])
        probs = cascade_probs(layers, ch, params, mixtures=mixtures)[-1]
        out[item] = layer_context(probs.half().float(), params, mixtures)
    return out


def grow_cascade(
    ann: PoseAnnotations,
    items: list[list[tuple[int, bool]]],
    cfg: TrainConfig,
    params: EstimatorParams,
    mixtures: PairwiseMixtures,
    rng: np.random.Generator,
    checkpoint: Path | None = None,
) -> tuple[list[Forest], dict[str, float]]:
    """The cascade's layers, each on its share of the images (items: one list of (annotation
    index, flipped) per layer, see train; mixtures: the PSM's, for the contexts), and the
    seconds each took.

    checkpoint: a folder where each layer is written when grown, with the random state after
    it; the layers found there are read instead of grown again (a resumed training ends with
    the layers of an uninterrupted one)."""
    timings = {}
    layers: list[Forest] = []
    for depth, (n_trees, share) in enumerate(zip(cfg.trees, items, strict=True), 1):
        t0 = time.perf_counter()
        saved = None if checkpoint is None else checkpoint / f"forest{depth}.pt"
        if saved is not None and saved.is_file():
            state = torch.load(saved, weights_only=False)
            layers.append(Forest.from_dict(state["forest"]))
            rng.bit_generator.state = state["rng"]
            timings[f"layer{depth}"] = state["seconds"]
            log.info("layer %d: read from %s", depth, saved)
            continue
        contexts = None
        if layers:
            contexts = cascade_contexts(ann, share, layers, params, mixtures)
            log.info(
                "layer-%d inputs of %d images: %.1fs", depth, len(share), time.perf_counter() - t0
            )
        desc = f"layer {depth} trees"
        layers.append(grow_layer(ann, share, contexts, n_trees, cfg, params, rng, desc))
        timings[f"layer{depth}"] = time.perf_counter() - t0
        if saved is not None:
            state = {
                "forest": layers[-1].to_dict(),
                "rng": rng.bit_generator.state,
                "seconds": timings[f"layer{depth}"],
            }
            save_checkpoint(state, saved)
    return layers, timings
