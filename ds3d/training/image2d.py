"""train(): the whole 2D model, a forest cascade, the PSM's pairwise mixtures and a network (the
joint network, a second unary, or for a model without one the facing CNN), written as one model
directory (ds3d.image2d.model_files).

The joint network learns person-centric labels from the whole person, and so which arm is the
right one. Without it, whether the person faces the camera is learnt by the facing CNN. Labels
can be observer-centric outright (ModelParams.observer_labels): in every training image the arm
whose shoulder is on the image's left is called "right", and likewise the leg by its hip, which
is what local image evidence can tell.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ds3d.data.lsp import PoseAnnotations
from ds3d.image2d.model_files import record_metrics, save_model
from ds3d.image2d.params import EstimatorParams
from ds3d.training.config import TrainConfig
from ds3d.training.facing import fit_facing
from ds3d.training.forests import grow_cascade
from ds3d.training.images import training_annotations
from ds3d.training.jointnet import fit_jointnet
from ds3d.training.psm import fit_psm
from ds3d.util.progress import set_quiet

log = logging.getLogger(__name__)

CHECKPOINT_DIR = "checkpoint"  # in a model folder while it trains


def fit_on_one_thread(
    fit, ann: PoseAnnotations, params: EstimatorParams, cfg: TrainConfig, log_level: int
) -> tuple[dict[str, Tensor], float]:
    """fit_facing or fit_jointnet on one torch thread (train runs each in a worker process
    beside the forests): the state dict and the seconds it took. One thread, because the
    result depends on the thread count (the order in which gradients are summed). No progress
    bar here: the terminal shows the forests'; the network's log lines still come."""
    logging.basicConfig(level=log_level, format="%(asctime)s %(message)s")
    set_quiet(True)
    torch.set_num_threads(1)
    return fit(ann, params, cfg)


def train(
    cfg: TrainConfig,
    params: EstimatorParams,
    out_dir: Path,
    evaluate=None,
    resume: bool = False,
) -> dict:
    """Train the cascade, the PSM and one network (the joint network, or the facing CNN where
    cfg.jointnet_epochs is 0); write them with manifest.json to out_dir.

    Progress is saved in out_dir/CHECKPOINT_DIR (each forest layer once grown, the joint
    network after every epoch) and removed at the end; `resume` continues from it, to the
    model an uninterrupted run gives, else it starts afresh.
    evaluate: None or a callable(out_dir) -> dict of metrics, stored in the manifest.
    Returns the manifest dict.
    """
    checkpoint = out_dir / CHECKPOINT_DIR
    if not resume:
        shutil.rmtree(checkpoint, ignore_errors=True)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    train_ann = training_annotations(cfg)[0]
    # One disjoint share of the images per layer: a context layer reads the maps of the layers
    # before it on images they never saw (stacking without leakage). Layer 1 draws a flip per
    # tree and image; later layers read precomputed maps, so each of their images has one flip.
    shares = np.array_split(rng.permutation(len(train_ann)), len(cfg.trees))
    items = [[(int(i), False) for i in shares[0]]] + [
        [(int(i), bool(rng.random() < 0.5)) for i in share] for share in shares[1:]
    ]
    t0 = time.perf_counter()
    mixtures = fit_psm(train_ann, cfg, params)  # first: the cascade's contexts may run the PSM
    timings = {"psm": time.perf_counter() - t0}
    # The network needs nothing from the forests: it trains beside them in a process of its own
    # on one thread (scikit-learn grows a tree on one core), so that it is the same whatever
    # --threads says. The joint network settles left and right itself
    # (ds3d.image2d.left_right); the facing CNN serves models without one.
    fit: Callable[[PoseAnnotations, EstimatorParams, TrainConfig], tuple[dict, float]]
    if cfg.jointnet_epochs:
        name, fit = "jointnet", partial(fit_jointnet, checkpoint=checkpoint / "jointnet.pt")
    else:
        name, fit = "facing", fit_facing
    spawn = multiprocessing.get_context("spawn")
    threads = torch.get_num_threads()
    # The network's process keeps one core busy. Threads beyond the cores left spin against
    # it: with --threads 2 on 2 cores, a tree's features took 480-510 s beside the facing CNN
    # against 23-26 s once it had finished.
    torch.set_num_threads(max(1, min(threads, (os.cpu_count() or 1) - 1)))
    try:
        with ProcessPoolExecutor(1, mp_context=spawn) as pool:
            net = pool.submit(
                fit_on_one_thread, fit, train_ann, params, cfg, log.getEffectiveLevel()
            )
            layers, layer_timings = grow_cascade(
                train_ann, items, cfg, params, mixtures, rng, checkpoint
            )
            state, timings[name] = net.result()
    finally:
        torch.set_num_threads(threads)
    timings.update(layer_timings)
    timings["total"] = time.perf_counter() - t0
    provenance = {
        "data": {
            "train": f"LSP train im0001-im{1000 - cfg.n_val:04d}"
            + f" + LSPet im00001-im{10000 - cfg.lspet_val:05d}"
            + (f", {cfg.max_images} of them drawn with the seed" if cfg.max_images else ""),
            "validation": f"LSP train im{1001 - cfg.n_val:04d}-im1000"
            + (f" and LSPet im{10001 - cfg.lspet_val:05d}-im10000" if cfg.lspet_val else "")
            + " (not trained on)",
            "n_train_images": len(train_ann),
            "terms": "LSP/LSPet: research use only (Johnson & Everingham, BMVC 2010, CVPR 2011)",
        },
        "seed": cfg.seed,
        "train_config": asdict(cfg),
    }
    shape = cfg.jointnet_shape() if name == "jointnet" else None
    manifest = save_model(
        out_dir, layers, mixtures, {name: state}, params, provenance, timings, shape
    )
    shutil.rmtree(checkpoint, ignore_errors=True)
    if evaluate is not None:
        manifest = record_metrics(out_dir, "validation", evaluate(out_dir))
    return manifest
