"""The facing CNN (ds3d.image2d.facing) of a model without a joint network: whether the person
faces the camera (then person-centric = observer-centric labels) or away (then left and right
swap), learnt from the image around the torso."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ds3d.data.lsp import PoseAnnotations
from ds3d.image2d.facing import FacingNet, crop, crop_centre
from ds3d.image2d.features import lab_channels
from ds3d.image2d.params import EstimatorParams
from ds3d.skeleton import L_HIP, L_SHOULDER, NECK, R_HIP, R_SHOULDER
from ds3d.training.config import TrainConfig
from ds3d.training.images import faces_camera, load_training_image

log = logging.getLogger(__name__)

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


def train_facing(windows: Tensor, labels: Tensor, cfg: TrainConfig) -> FacingNet:
    """The facing model (ds3d.image2d.facing) trained on facing_windows: AdamW, a one-cycle
    learning rate peaking at `facing_lr`, `facing_epochs` epochs of batches of FACING_BATCH;
    every draw cuts a CROP window at a random scale (x0.87-1.15) and shift (+-8 px), mirrors
    it at random (facing the camera is mirror-invariant, so the label stays) and jitters its
    lightness and colour (the jitter and the epochs: docs/tuning.md). Seeded by seed * 1000 + 7
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


def fit_facing(
    ann: PoseAnnotations, params: EstimatorParams, cfg: TrainConfig
) -> tuple[dict, float]:
    """The facing CNN's state dict, from facing_windows + train_facing, and the seconds it
    took."""
    t0 = time.perf_counter()
    net = train_facing(*facing_windows(ann, params), cfg)
    return net.state_dict(), time.perf_counter() - t0
