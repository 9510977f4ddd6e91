"""The 2D stage's training images: LSP train (im0001-im1000, minus the last `n_val` images, held
out for validation) and LSPet (10,000, minus the last `lspet_val`, held out likewise), each
rescaled so that its person spans `canonical_extent` px (ModelParams), optionally mirrored; and
the relabellings of their joints (observer-centric labels, whether the person faces the camera)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ds3d.data.lsp import PoseAnnotations, load_lsp, load_lspet
from ds3d.image2d.crops import resize_image
from ds3d.image2d.facing import observer_order
from ds3d.image2d.params import EstimatorParams
from ds3d.io.images import read_image
from ds3d.skeleton import FLIP, L_SHOULDER, R_SHOULDER
from ds3d.training.config import TrainConfig


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


def training_annotations(
    cfg: TrainConfig,
) -> tuple[PoseAnnotations, PoseAnnotations, PoseAnnotations]:
    """(train, val, lspet_val): LSP train minus its last n_val images + LSPet minus its last
    lspet_val; val = those n_val LSP images, lspet_val those LSPet ones (none when 0)."""
    lsp = load_lsp(split="train")
    n_fit = len(lsp) - cfg.n_val
    lspet = load_lspet()
    n_fit_lspet = len(lspet) - cfg.lspet_val
    train = lsp.subset(range(n_fit)).concat(lspet.subset(range(n_fit_lspet)))
    val = lsp.subset(range(n_fit, len(lsp)))
    lspet_val = lspet.subset(range(n_fit_lspet, len(lspet)))
    if cfg.max_images is not None:
        keep = np.random.default_rng(cfg.seed).choice(len(train), cfg.max_images, replace=False)
        train = train.subset(np.sort(keep))
    return train, val, lspet_val
