"""Training of the lifting prior (ds3d.mocap.prior) on a pose database's 3D poses alone.

Every batch draws fresh 2D-3D pairs from the database's body-frame poses (`draw`):
- mirrored (left and right swapped) half the time;
- each bone group scaled by exp(N(0, sd_g)): other people's proportions, and other
  laboratories' marker placements (Human3.6M's and CMU's hip widths differ by a third); sd_g in
  proportion to how much people's groups differ (ds3d.fit.bones.GROUP_LOG_SD: a head or a
  pelvis more than a forearm), bone_sd their RMS;
- seen by a camera at a random azimuth, elevation and roll, at a random distance (log-uniform),
  as photos are taken; then as the prior sees a query, through the camera turned to look at
  the person (ds3d.mocap.prior.look_at);
- some joints hidden (their flags off, coordinates zeroed);
- Gaussian noise on the normalised 2D joints: a per-pose sigma, uniform up to noise_sd, a share
  of the poses clean.
Three networks learn from such draws, one after the other: the clean lifting network from draws
without noise or hidden joints, the noisy one from draws with both (each the mean joint distance
in mm to the pose in the turned camera's orientation), and the noise estimator the draws' sigma
(the mean absolute error). AdamW with a one-cycle learning rate; seeded, so that a run is
reproducible on as many threads.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import torch
from torch import Tensor

from ds3d.fit.bones import group_spread, scaling_map
from ds3d.fit.camera import rotation_matrix
from ds3d.mocap.database import PoseDatabase
from ds3d.mocap.normalize import normalize_2d
from ds3d.mocap.prior import (
    NETWORKS,
    LiftingPrior,
    PriorShape,
    ResidualMLP,
    lifted,
    look_at,
    mirrored,
    prior_features,
)
from ds3d.mocap.retrieval import database_digest
from ds3d.skeleton import BONE_GROUPS, NUM_JOINTS
from ds3d.util.progress import progress

log = logging.getLogger(__name__)

NOISE_SHAPE = PriorShape(width=256, blocks=1, dropout=0.0, outputs=1)  # the estimator's


@dataclass(frozen=True)
class PriorTraining:
    """How a prior is trained (every field is recorded in its manifest). The camera's ranges
    and the noise were chosen on Human3.6M S9 with S1, S5-S8's database (docs/tuning.md)."""

    steps: int = 20_000  # each lifting network's
    noise_steps: int = 10_000  # the noise estimator's
    batch: int = 256
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    shape: PriorShape = field(default_factory=PriorShape)  # each lifting network's
    noise_shape: PriorShape = field(default_factory=lambda: NOISE_SHAPE)
    # the RMS over the bone groups of the sd of their log scales (ds3d.fit.bones.group_spread):
    # wider than people's (0.064) for other laboratories' joint placements
    bone_sd: float = 0.16
    elevation_deg: tuple[float, float] = (-5.0, 30.0)  # the camera above the person, uniform
    roll_sd_deg: float = 5.0
    distance_mm: tuple[float, float] = (3000.0, 9000.0)  # log-uniform
    hidden: float = 0.2  # share of poses with 1 to MAX_HIDDEN joints hidden
    noise_sd: float = 0.08  # the largest per-pose sigma, normalised units (y spans [-1, 1])
    clean: float = 0.3  # share of the noisy network's and the estimator's poses without noise
    # (the clean network's: all, and none with hidden joints: learning them cost it 2.4 mm on S9)
    validation: int = 4096  # pairs drawn once (by seed + 1) to report the losses on


MAX_HIDDEN = 4


@dataclass
class Pairs:
    """B training pairs: features (B, FEATURES) the networks' input; target (B, 14, 3) mm, the
    pose in the orientation of the camera that saw it (turned to look at the person); sigma (B,)
    the noise added, normalised units."""

    features: Tensor
    target: Tensor
    sigma: Tensor


def view_rotations(n: int, cfg: PriorTraining, generator: torch.Generator) -> Tensor:
    """(n, 3, 3) random views, body frame -> camera-oriented: R_z(roll) R_x(elevation)
    R_y(azimuth), elevation and azimuth as ds3d.mocap.views composes them."""
    azimuth = torch.rand(n, generator=generator) * 2 * math.pi
    low, high = (math.radians(v) for v in cfg.elevation_deg)
    elevation = low + torch.rand(n, generator=generator) * (high - low)
    roll = torch.randn(n, generator=generator) * math.radians(cfg.roll_sd_deg)
    zero = torch.zeros(n)

    def about(axis: int, angle: Tensor) -> Tensor:
        return rotation_matrix(torch.stack([angle if i == axis else zero for i in range(3)], -1))

    return about(2, roll) @ about(0, elevation) @ about(1, azimuth)


def draw(poses: Tensor, cfg: PriorTraining, generator: torch.Generator) -> Pairs:
    """A batch of cfg.batch pairs from body-frame poses (N, 14, 3) mm (module docstring)."""
    b = cfg.batch

    def chance(p: float) -> Tensor:
        return torch.rand(b, generator=generator) < p

    pose = poses[torch.randint(len(poses), (b,), generator=generator)]
    pose = torch.where(chance(0.5)[:, None, None], mirrored(pose), pose)
    log_scales = torch.randn(b, len(BONE_GROUPS), generator=generator) * group_spread(cfg.bone_sd)
    views = view_rotations(b, cfg, generator).transpose(-1, -2)
    target = pose @ views  # the database's proportions: the fit rescales to the person's
    seen = (scaling_map(log_scales.exp()) @ pose) @ views  # camera-oriented

    hiding = chance(cfg.hidden)
    count = torch.randint(1, MAX_HIDDEN + 1, (b,), generator=generator)
    rank = torch.rand(b, NUM_JOINTS, generator=generator).argsort(-1).argsort(-1)
    visible = ~(hiding[:, None] & (rank < count[:, None]))

    low, high = (math.log(v) for v in cfg.distance_mm)
    distance = (low + torch.rand(b, generator=generator) * (high - low)).exp()
    rays = seen + torch.stack([torch.zeros(b), torch.zeros(b), distance], -1)[:, None]
    points, turn = look_at(rays, visible)

    sigma = torch.rand(b, generator=generator) * cfg.noise_sd * ~chance(cfg.clean)
    noise = torch.randn(b, NUM_JOINTS, 2, generator=generator) * sigma[:, None, None]
    features = prior_features(normalize_2d(points, visible) + noise, visible)
    return Pairs(features, target @ turn.transpose(-1, -2), sigma)


def joint_distance(net: ResidualMLP, pairs: Pairs) -> Tensor:
    """A lifting network's loss: the mean joint distance (mm) of its poses to the targets."""
    return (lifted(net, pairs.features) - pairs.target).norm(dim=-1).mean()


def noise_error(net: ResidualMLP, pairs: Pairs) -> Tensor:
    """The noise estimator's loss: the mean absolute error of its sigma (normalised units)."""
    return (net(pairs.features)[:, 0] - pairs.sigma).abs().mean()


Loss = Callable[[ResidualMLP, Pairs], Tensor]


def train_network(
    db: PoseDatabase, cfg: PriorTraining, shape: PriorShape, steps: int, loss: Loss, seed: int
) -> tuple[ResidualMLP, dict]:
    """A ResidualMLP of `shape` trained `steps` steps on cfg's draws of db's poses, and its
    metrics: the loss over the last 1,000 steps and on the validation pairs."""
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed + 4)  # dropout
    held = draw(
        db.poses, replace(cfg, batch=cfg.validation), torch.Generator().manual_seed(seed + 1)
    )
    net = ResidualMLP(shape)
    opt = torch.optim.AdamW(net.parameters(), cfg.lr, weight_decay=cfg.weight_decay)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=steps)
    recent = list[float]()
    net.train()
    for step in progress(range(steps), desc="prior", unit="step"):
        value = loss(net, draw(db.poses, cfg, generator))
        opt.zero_grad()
        value.backward()
        opt.step()
        schedule.step()
        recent = [*recent[-999:], float(value.detach())]
        if (step + 1) % 5000 == 0:
            log.info("prior step %d: loss %.4g", step + 1, sum(recent) / len(recent))
    net.eval()
    with torch.inference_mode():
        validation = float(loss(net, held))
    return net, {
        "train_loss": round(sum(recent) / len(recent), 4),
        "validation": round(validation, 4),
    }


def train_prior(db: PoseDatabase, cfg: PriorTraining) -> LiftingPrior:
    """NETWORKS trained on db's poses (module docstring); the manifest records the database,
    the settings, the seconds and each network's losses (mm for the lifting networks, normalised
    units for the noise estimator)."""
    start = time.perf_counter()
    plans = {  # name: (its draws, shape, steps, loss)
        "clean": (replace(cfg, clean=1.0, hidden=0.0), cfg.shape, cfg.steps, joint_distance),
        "noisy": (cfg, cfg.shape, cfg.steps, joint_distance),
        "noise": (cfg, cfg.noise_shape, cfg.noise_steps, noise_error),
    }
    nets, metrics = {}, {}
    for k, name in enumerate(NETWORKS):
        draws, shape, steps, loss = plans[name]
        log.info("prior: the %s network, %d steps", name, steps)
        nets[name], metrics[name] = train_network(
            db, draws, shape, steps, loss, cfg.seed * 1000 + 100 * k + 13
        )
    manifest = {
        "database": {
            "source": db.manifest.get("source"),
            "subjects": db.manifest.get("subjects"),
            "files": db.manifest.get("files"),
            "poses": len(db.poses),
            "digest": database_digest(db),
        },
        "seed": cfg.seed,
        "training": asdict(cfg),
        "parameters": {
            name: sum(p.numel() for p in net.parameters()) for name, net in nets.items()
        },
        "seconds": round(time.perf_counter() - start, 1),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "metrics": metrics,
    }
    return LiftingPrior(nets, manifest)
