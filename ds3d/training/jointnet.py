"""Training of the joint network (ds3d.image2d.jointnet) on the 2D stage's training images.

The data is one WINDOW x WINDOW window of Lab channels per image at the working scale, around
the person (jointnet_windows). Every draw cuts a CROP x CROP view from it (view_windows), rotated
(+-ROTATION degrees), zoomed (x ZOOM[0]-ZOOM[1]: the pyramid's residual scale error and more),
shifted, mirrored at random (left and right labels swapped with it) and jittered in lightness
and colour; a share of them (TrainConfig.jointnet_edge_cut) cut by an image edge, the joints past
it still targets (edge_cut); then, where TrainConfig.jointnet_degraded says so, made to look less
like an LSP crop (degrade): occluded by a patch of another view, blurred as a small person scaled
up is. The target of a joint is a Gaussian of SIGMA output cells around it,
normalised over the cells; the loss is the cross-entropy between it and the log-softmax of the
joint's map, over the joints whose position is annotated (PoseAnnotations.located) and that lie
in the view.

bfloat16 autocast on a CPU that computes it (jointnet.CPU_BFLOAT16): twice the speed of float32
on this machine's cores (docs/tuning.md). Seeded by seed * 1000 + 11 (torch's generator).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from ds3d.data.lsp import PoseAnnotations
from ds3d.image2d.facing import crop
from ds3d.image2d.features import lab_channels
from ds3d.image2d.jointnet import CPU_BFLOAT16, STRIDE, JointNet, JointNetShape
from ds3d.image2d.params import EstimatorParams
from ds3d.skeleton import FLIP, NUM_JOINTS
from ds3d.training.checkpoint import save_checkpoint
from ds3d.training.config import TrainConfig
from ds3d.training.images import load_training_image
from ds3d.util.progress import progress

log = logging.getLogger(__name__)

WINDOW = 176  # px at the working scale, kept per training image
CROP = 128  # px, the network's training input
ROTATION = 40.0  # degrees
ZOOM = (1 / 1.3, 1 / 0.7)  # window px per input px: the person at 0.7-1.3 times its size
SHIFT = 12.0  # px
SIGMA = 1.0  # output cells
BATCH = 64
# A view cut by an image edge (edge_cut; how often: TrainConfig.jointnet_edge_cut)
EDGE_SIDES = (0.2, 0.2, 0.1, 0.5)  # the edge at the left, right, top, bottom (legs cut most)
EDGE_SHARE = (0.1, 0.4)  # of the person's extent beyond the edge
# degrade: how often each happens to a view, and how much
OCCLUSION = 0.3  # a view with a rectangle of another view pasted over it
OCCLUDER = (0.15, 0.4)  # its sides, of the view's
LOW_RESOLUTION = 0.3  # a view shrunk by a factor of 1.5-3 and scaled back up
GREY = 0.1  # a view without colour


def augment(
    windows: Tensor,
    joints: Tensor,
    located: Tensor,
    degraded: bool = True,
    cut: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """Random views of a batch (view_windows; a share `cut` of them cut by an image edge,
    edge_cut; then degrade where `degraded`): windows (b, 3, WINDOW, WINDOW), joints (b, 14, 2)
    window px, located (b, 14) -> (b, 3, CROP, CROP) float32, joints (b, 14, 2) in view px,
    (b, 14) bool of the located joints that lie in the view."""
    views, pts, known = view_windows(windows, joints, located)
    if cut:  # drawn only then: a training without cuts keeps its random stream
        views = edge_cut(views, pts, known, torch.rand(len(views)) < cut)
    return degrade(views, pts, known) if degraded else (views, pts, known)


def view_windows(windows: Tensor, joints: Tensor, located: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The geometric and colour part of augment: rotated, zoomed, shifted, mirrored views, with
    augment's arguments and results."""
    b = len(windows)
    angle = torch.empty(b).uniform_(-ROTATION, ROTATION) * (math.pi / 180)
    zoom = torch.empty(b).uniform_(*ZOOM)
    shift = torch.empty(b, 2).uniform_(-SHIFT, SHIFT)
    flip = torch.rand(b) < 0.5
    # View px v (centred) reads window px  c_w + shift + zoom * R(angle) * (mirror) v.
    cos, sin = torch.cos(angle) * zoom, torch.sin(angle) * zoom
    sx = torch.where(flip, -1.0, 1.0)
    a = torch.stack([torch.stack([cos * sx, -sin], -1), torch.stack([sin * sx, cos], -1)], 1)
    half_w, half_c = (WINDOW - 1) / 2, (CROP - 1) / 2
    # affine_grid works in [-1, 1] units with align_corners=True: scale by the two halves.
    theta = torch.cat([a * (half_c / half_w), (shift / half_w)[:, :, None]], 2)
    grid = F.affine_grid(theta, [b, 3, CROP, CROP], align_corners=True)
    views = F.grid_sample(windows.float(), grid, mode="bilinear", align_corners=True)
    views[:, 0] += torch.empty(b, 1, 1).uniform_(-0.1, 0.1)  # lightness
    views[:, 1:] = views[:, 1:] * torch.empty(b, 1, 1, 1).uniform_(0.7, 1.3)
    views[:, 1:] += torch.empty(b, 2, 1, 1).uniform_(-0.05, 0.05)
    # Joints: v = A^-1 (w - c_w - shift).
    rel = joints - half_w - shift[:, None, :]
    out = torch.linalg.solve(a[:, None], rel[..., None])[..., 0] + half_c
    order = torch.tensor(FLIP)
    out = torch.where(flip[:, None, None], out[:, order], out)
    known = torch.where(flip[:, None], located[:, order], located)
    inside = ((out >= 0) & (out <= CROP - 1)).all(-1)
    return views, out, known & inside


def degrade(views: Tensor, joints: Tensor, known: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Views (b, 3, CROP, CROP) with their joints (b, 14, 2) view px and known (b, 14) bool made
    to look like people in other photos than LSP's tight, sharp crops (the rates above): a
    patch of another view of the batch over them (occlude; the joints under it stay known: the
    network learns to place hidden joints from the rest of the person), shrunk and scaled back
    up (low_resolution), without colour. Returns the same three, views changed in place."""
    b = len(views)
    views = occlude(views, torch.rand(b) < OCCLUSION)
    views = low_resolution(views, torch.rand(b) < LOW_RESOLUTION)
    views[:, 1:] *= (torch.rand(b) >= GREY)[:, None, None, None]
    return views, joints, known


def edge_cut(views: Tensor, joints: Tensor, known: Tensor, chosen: Tensor) -> Tensor:
    """The chosen views (chosen: (b,) bool) cut by an image edge (EDGE_SIDES) that leaves a drawn
    share (EDGE_SHARE) of their known joints' extent beyond it: those pixels zeros (what the
    network sees beyond a photo's border). The joints beyond it stay known: the network learns
    where a joint the photo cuts off lies, from the person it sees, and the 2D stage's grid
    reaches past the image's edges for it. Returns views."""
    b = len(views)
    side = torch.multinomial(torch.tensor(EDGE_SIDES), b, replacement=True)  # (b,)
    share = torch.empty(b).uniform_(*EDGE_SHARE)
    axis = (side >= 2).long()  # 0: x (left, right edges), 1: y (top, bottom)
    far = side % 2 == 1  # the right or bottom edge: what lies beyond is the high coordinates
    coord = joints.gather(2, axis[:, None, None].expand(-1, joints.shape[1], 1))[..., 0]
    low = torch.where(known, coord, math.inf).amin(1)
    high = torch.where(known, coord, -math.inf).amax(1)
    cut = torch.where(far, high - share * (high - low), low + share * (high - low))
    chosen = chosen & known.any(1)
    px = torch.arange(views.shape[-1], dtype=torch.float32)
    pos = torch.where(axis[:, None, None] == 0, px[None, None, :], px[None, :, None])  # (b,H,W)
    cut_px = cut[:, None, None]
    beyond = torch.where(far[:, None, None], pos > cut_px, pos < cut_px) & chosen[:, None, None]
    views.masked_fill_(beyond[:, None], 0.0)
    return views


def occlude(views: Tensor, chosen: Tensor) -> Tensor:
    """The chosen views (chosen: (b,) bool) with a rectangle (sides OCCLUDER of the view's) taken
    from another view of the batch at the same place."""
    b, _, h, w = views.shape
    size = torch.empty(b, 2).uniform_(*OCCLUDER) * torch.tensor([w, h])
    corner = torch.rand(b, 2) * (torch.tensor([w, h]) - size)
    ys, xs = torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32)
    in_x = (xs >= corner[:, :1]) & (xs < corner[:, :1] + size[:, :1])  # (b, W)
    in_y = (ys >= corner[:, 1:]) & (ys < corner[:, 1:] + size[:, 1:])  # (b, H)
    inside = in_y[:, :, None] & in_x[:, None, :] & chosen[:, None, None]
    others = views[torch.randperm(b)]
    return torch.where(inside[:, None], others, views)


def low_resolution(views: Tensor, chosen: Tensor) -> Tensor:
    """The chosen views (chosen: (b,) bool) shrunk by one drawn factor of 1.5-3 (area averaging)
    and scaled back up (bilinear): the look of a small person that the pyramid scales up."""
    rows = torch.nonzero(chosen).view(-1)
    if len(rows) == 0:
        return views
    size = views.shape[-2:]
    factor = float(torch.empty(()).uniform_(1.5, 3.0))
    small = [round(n / factor) for n in size]
    shrunk = F.interpolate(views[rows], size=small, mode="area")
    views[rows] = F.interpolate(shrunk, size=size, mode="bilinear", align_corners=False)
    return views


def soft_targets(joints: Tensor, size: int) -> Tensor:
    """Gaussian targets on a size x size output grid: joints (b, 14, 2) view px ->
    (b, 14, size * size), each row summing to 1 (cell (u, v) is view px (STRIDE u, STRIDE v));
    all zero for a joint too far off the grid (its Gaussian underflows), never NaN."""
    cells = torch.arange(size, dtype=torch.float32)
    g = joints / STRIDE
    dx = cells[None, None, None, :] - g[..., 0, None, None]
    dy = cells[None, None, :, None] - g[..., 1, None, None]
    t = torch.exp(-0.5 * (dx * dx + dy * dy) / SIGMA**2).reshape(*joints.shape[:2], -1)
    return t / t.sum(-1, keepdim=True).clamp_min(1e-30)


def jointnet_loss(logits: Tensor, joints: Tensor, mask: Tensor) -> Tensor:
    """Mean cross-entropy of the maps' spatial log-softmax against soft_targets, over the masked
    joints. logits: (b, 14, s, s); joints: (b, 14, 2) view px; mask: (b, 14) bool."""
    logp = torch.log_softmax(logits.float().flatten(2), -1)
    ce = -(soft_targets(joints, logits.shape[-1]) * logp).sum(-1)  # (b, 14)
    return (ce * mask).sum() / mask.sum().clamp_min(1)


def train_jointnet(
    windows: Tensor,
    joints: Tensor,
    located: Tensor,
    epochs: int,
    lr: float,
    seed: int,
    shape: JointNetShape = JointNetShape(),
    checkpoint: Path | None = None,
    degraded: bool = False,
    cut: float = 0.0,
    init: dict | None = None,
) -> tuple[JointNet, float]:
    """JointNet of `shape` trained on jointnet_windows: AdamW, a one-cycle learning rate peaking
    at lr, `epochs` epochs of batches of BATCH random views (augment, `degraded` or not, a share
    `cut` cut by an image edge), from the state dict `init` where given (a network to go on
    training), else from scratch. Returns the network and the seconds its epochs took (over
    every run of a resumed training).

    checkpoint: where the state after every epoch is written (network, optimiser, schedule,
    random state); a run that finds one there, of the same training, resumes after its epoch and
    ends with the network an uninterrupted run would have (on as many threads).
    """
    torch.manual_seed(seed * 1000 + 11)
    # Module.to takes memory_format (as documented); torch's overloads of it leave it out.
    net = JointNet(shape).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    if init is not None:
        net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in init.items()})
    opt = torch.optim.AdamW(net.parameters(), lr, weight_decay=1e-4)
    steps = epochs * -(-len(windows) // BATCH)
    schedule = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps)
    run = {"epochs": epochs, "lr": lr, "seed": seed, "shape": asdict(shape), "n": len(windows)}
    run |= {"degraded": degraded} | ({"cut": cut} if cut else {}) | ({"init": True} if init else {})
    first, seconds = 0, 0.0
    if checkpoint is not None and checkpoint.is_file():
        first, seconds = _resume(checkpoint, run, net, opt, schedule)
        log.info("jointnet: resumed after epoch %d from %s", first, checkpoint)
    net.train()
    for epoch in progress(range(first, epochs), desc="jointnet", unit="epoch"):
        t0 = time.perf_counter()
        total = 0.0
        for rows in torch.randperm(len(windows)).split(BATCH):
            views, pts, mask = augment(windows[rows], joints[rows], located[rows], degraded, cut)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=CPU_BFLOAT16):
                logits = net(views.contiguous(memory_format=torch.channels_last))
            loss = jointnet_loss(logits, pts, mask)
            opt.zero_grad()
            loss.backward()
            opt.step()
            schedule.step()
            total += float(loss.detach()) * len(rows)
        seconds += time.perf_counter() - t0
        log.info("jointnet epoch %d: loss %.4f (%.0f s)", epoch + 1, total / len(windows), seconds)
        if checkpoint is not None:
            _save_checkpoint(checkpoint, run, epoch + 1, seconds, net, opt, schedule)
    return net.eval(), seconds


def _save_checkpoint(path: Path, run: dict, epoch: int, seconds: float, net, opt, schedule):
    """The training state after `epoch` epochs (`seconds` in all)."""
    state = {
        "run": run,
        "epoch": epoch,
        "seconds": seconds,
        "net": net.state_dict(),
        "opt": opt.state_dict(),
        "schedule": schedule.state_dict(),
        "rng": torch.get_rng_state(),
    }
    save_checkpoint(state, path)


def _resume(path: Path, run: dict, net, opt, schedule) -> tuple[int, float]:
    """Load a checkpoint of the same training `run` into net, opt and schedule and the random
    state; returns the epochs it had done and their seconds. Raises ValueError for another
    training's."""
    state = torch.load(path, weights_only=False)
    if state["run"] != run:
        raise ValueError(f"{path} is a checkpoint of another training: {state['run']} != {run}")
    net.load_state_dict(state["net"])
    opt.load_state_dict(state["opt"])
    schedule.load_state_dict(state["schedule"])
    torch.set_rng_state(state["rng"])
    return state["epoch"], state["seconds"]


def jointnet_windows(
    ann: PoseAnnotations, params: EstimatorParams
) -> tuple[Tensor, Tensor, Tensor]:
    """The joint network's training data (below): per image, a window of
    WINDOW x WINDOW px of Lab / 100 at the working scale, centred on the box around its located
    joints; the joints in window px; which are located. Returns ((N, 3, WINDOW, WINDOW) float16,
    (N, 14, 2) float32 (x, y), (N, 14) bool)."""
    size = WINDOW
    windows = torch.empty(len(ann), 3, size, size, dtype=torch.float16)
    joints = torch.empty(len(ann), NUM_JOINTS, 2)
    located = torch.from_numpy(ann.located.copy())
    for i in progress(range(len(ann)), desc="jointnet windows", unit="img"):
        sample = load_training_image(ann, i, False, params)
        pts = torch.from_numpy(sample.joints)
        known = pts[located[i]] if located[i].sum() >= 2 else pts
        centre = ((known.min(0).values + known.max(0).values) / 2)[None]
        lab = lab_channels(torch.from_numpy(sample.image)[None])
        windows[i] = crop(lab, centre, size=size)[0].half()
        joints[i] = pts - centre + (size - 1) / 2
    return windows, joints, located


def fit_jointnet(
    ann: PoseAnnotations,
    params: EstimatorParams,
    cfg: TrainConfig,
    checkpoint: Path | None = None,
    init: dict | None = None,
) -> tuple[dict, float]:
    """The joint network's state dict, from jointnet_windows + train_jointnet (checkpointed to
    `checkpoint`, resumed from it when it holds this training's), its floats stored as float16
    (half the file; the network runs in bfloat16 anyway), and the seconds it took (the windows
    and every epoch)."""
    t0 = time.perf_counter()
    windows = jointnet_windows(ann, params)
    windows_seconds = time.perf_counter() - t0
    net, seconds = train_jointnet(
        *windows,
        cfg.jointnet_epochs,
        cfg.jointnet_lr,
        cfg.seed,
        cfg.jointnet_shape(),
        checkpoint,
        cfg.jointnet_degraded,
        cfg.jointnet_edge_cut,
        init,
    )
    state = {k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()}
    return state, windows_seconds + seconds
