"""The PSM's binaries (ds3d.image2d.psm) from the training poses at the working scale."""

from __future__ import annotations

import numpy as np
import torch

from ds3d.data.lsp import PoseAnnotations
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures, fit_pairwise_mixtures
from ds3d.skeleton import FLIP
from ds3d.training.config import TrainConfig
from ds3d.training.images import observer_centric, working_scale_joints


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
