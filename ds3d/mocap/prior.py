"""A lifting prior learnt from the pose database alone: 2D joints in, a 3D pose out, by small
networks (the residual MLP of Martinez et al., ICCV 2017) trained on the database's poses seen by
random virtual cameras (ds3d.training.prior), with no image.

The networks see a 2D pose as the retrieval does, translated and scaled so that its y extent
spans [-1, 1] (ds3d.mocap.normalize.normalize_2d), each joint with a flag saying whether it is
visible (a hidden joint's coordinates are zero). With the camera's intrinsics, the joints are
first seen from a virtual camera of the same centre turned to look at the person (`look_at`):
how a person off the optical axis looks is then how one on it does, and the networks never have
to learn the camera's field of view. The prior answers the pose in that camera's orientation
(x right, y down, z away from it), mm, root at the hip midpoint, and turns it back to the real
camera's.

A network trained on noisy 2D lifts clean 2D worse than one trained on clean 2D (docs/tuning.md:
6 mm on Human3.6M S9), and being told the noise level does not give it back. So the prior holds
two lifting networks, one trained on clean 2D and one on noisy, and a third network that
estimates the 2D's noise level from the pose alone; the answer is their blend, the noisy one's
share growing with the estimate (`NOISE_GATE`). Only the noisy one learnt poses with hidden
joints (the clean one lifts complete poses 2.4 mm better for not learning them): it alone lifts
those.

On disk, a prior is a folder (`<database>/prior/` beside the pose database it was trained on):
`prior.pt` (the networks' shapes and weights, `packed`) and `manifest.json` (seed, data,
settings, metrics).
"""

from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_linear_bn_eval

from ds3d.errors import DataFormatError
from ds3d.fit.camera import rotation_matrix
from ds3d.mocap.normalize import normalize_2d
from ds3d.skeleton import FLIP, NUM_JOINTS, hip_midpoint

PRIOR_DIR = "prior"  # the prior's folder inside its database's
OUTPUT_UNIT = 1000.0  # mm per unit of a lifting network's output: targets of order one
FEATURES = 3 * NUM_JOINTS  # x, y and visibility of each joint (prior_features)
# The estimated noise sigma (normalise_2d's units: a 2D pose's half height is 1) at and above
# which the noisy network alone answers; below it the clean one's share grows linearly to all of
# it at zero. 10 px of noise on a Human3.6M person is about 0.06. Chosen on S9 (docs/tuning.md).
NOISE_GATE = 0.04


@dataclass(frozen=True)
class PriorShape:
    """A network: a linear layer to `width` features, `blocks` residual blocks of two linear
    layers each (batch norm, ReLU, dropout), a linear layer to `outputs`."""

    width: int = 512
    blocks: int = 2
    dropout: float = 0.25
    outputs: int = 3 * NUM_JOINTS  # a pose; 1 for the noise estimator


class ResidualMLP(nn.Module):
    """(B, FEATURES) prior_features -> (B, shape.outputs)."""

    def __init__(self, shape: PriorShape = PriorShape()):
        super().__init__()
        self.shape = shape

        def layer(n_in: int) -> list[nn.Module]:
            return [
                nn.Linear(n_in, shape.width),
                nn.BatchNorm1d(shape.width),
                nn.ReLU(),
                nn.Dropout(shape.dropout),
            ]

        self.stem = nn.Sequential(*layer(FEATURES))
        self.blocks = nn.ModuleList(
            nn.Sequential(*layer(shape.width), *layer(shape.width)) for _ in range(shape.blocks)
        )
        self.head = nn.Linear(shape.width, shape.outputs)

    def forward(self, features: Tensor) -> Tensor:
        x = self.stem(features)
        for block in self.blocks:
            x = x + block(x)
        return self.head(x)


def folded(net: ResidualMLP) -> ResidualMLP:
    """For inference: a copy of `net` in eval mode whose every batch norm (an affine map per
    feature then) is folded into the linear layer before it, and whose dropouts (identities
    then) are gone: the same function, with one pass over the features less per layer."""
    out = copy.deepcopy(net).eval()

    def without_norms(layers: nn.Module) -> nn.Sequential:
        kept: list[nn.Module] = []
        for layer in layers.children():
            before = kept[-1] if kept else None
            if isinstance(layer, nn.BatchNorm1d) and isinstance(before, nn.Linear):
                kept[-1] = fuse_linear_bn_eval(before, layer)
            elif not isinstance(layer, nn.Dropout):
                kept.append(layer)
        return nn.Sequential(*kept)

    out.stem = without_norms(out.stem)
    out.blocks = nn.ModuleList(without_norms(block) for block in out.blocks)
    return out


def lifted(net: nn.Module, features: Tensor) -> Tensor:
    """A lifting network's pose of features (B, FEATURES): (B, 14, 3) mm, look-at frame."""
    return net(features).unflatten(-1, (NUM_JOINTS, 3)) * OUTPUT_UNIT


def mirrored(poses: Tensor) -> Tensor:
    """Poses (..., 14, 3) seen in a mirror: x negated and the left and right joints swapped, a
    pose a person could take (in the body frame, or in a camera's)."""
    return poses[..., list(FLIP), :] * poses.new_tensor([-1.0, 1.0, 1.0])


def look_at(rays: Tensor, visible: Tensor) -> tuple[Tensor, Tensor]:
    """The joints seen by a camera of the same centre turned to look at the visible joints'
    mean direction. rays: (B, 14, 3) directions from the camera centre (any length, z > 0);
    visible: (B, 14) bool. Returns their image in the turned camera (B, 14, 2), unit focal
    length, and the turn Q (B, 3, 3), the least rotation with Q c = (0, 0, 1) for the mean
    unit ray c (a point X of the camera is Q X in the turned one)."""
    unit = rays / rays.norm(dim=-1, keepdim=True)
    m = visible.to(unit.dtype)[..., None]
    centre = (unit * m).sum(-2) / m.sum(-2).clamp_min(1)
    centre = centre / centre.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # axis c x z, angle atan2(|c x z|, c . z); rotation_matrix is smooth at a zero angle
    axis = torch.stack([centre[:, 1], -centre[:, 0], torch.zeros_like(centre[:, 0])], -1)
    sine = axis.norm(dim=-1, keepdim=True)
    angle = torch.atan2(sine, centre[:, 2:3])
    turn = rotation_matrix(axis * torch.where(sine > 1e-12, angle / sine.clamp_min(1e-12), 1.0))
    turned = rays @ turn.transpose(-1, -2)
    return turned[..., :2] / turned[..., 2:3].clamp_min(1e-6), turn


def camera_rays(joints_2d: Tensor, intrinsics: Tensor) -> Tensor:
    """Pixels (B, 14, 2) -> their rays K^-1 (u, v, 1) (B, 14, 3) under intrinsics (B, 3, 3);
    under a singular K (no camera has one, but a request may), (u, v, 1) as if K were I."""
    homogeneous = torch.cat([joints_2d, torch.ones_like(joints_2d[..., :1])], -1)
    inverse, info = torch.linalg.inv_ex(intrinsics)
    eye = torch.eye(3, dtype=inverse.dtype, device=inverse.device)
    inverse = torch.where((info != 0)[:, None, None], eye, inverse)
    return homogeneous @ inverse.transpose(-1, -2)


def prior_features(points: Tensor, visible: Tensor) -> Tensor:
    """The networks' input: points (B, 14, 2) (any unit: the image of look_at, or pixels
    without intrinsics), visible (B, 14) bool -> (B, FEATURES): normalize_2d's coordinates (zero
    where hidden) and the visibility flags."""
    normalised = normalize_2d(points, visible)
    return torch.cat([normalised.flatten(1), visible.to(normalised.dtype)], 1)


def query_view(
    joints_2d: Tensor, visible: Tensor, intrinsics: Tensor | None
) -> tuple[Tensor, Tensor | None]:
    """The points the networks see of a 2D pose (B, 14, 2) px: with intrinsics (B, 3, 3), the
    image of look_at, and its turn (B, 3, 3); without (weak perspective), the pixels as they are
    (an orthographic view) and None."""
    if intrinsics is None:
        return joints_2d, None
    return look_at(camera_rays(joints_2d, intrinsics), visible)


NETWORKS = ("clean", "noisy", "noise")  # the two lifting networks and the noise estimator


class LiftingPrior:
    """The trained networks on a device, in eval mode: `prior(joints_2d, visible, intrinsics)`.
    nets: NETWORKS' ResidualMLPs by name."""

    def __init__(
        self, nets: dict[str, ResidualMLP], manifest: dict, device: str | torch.device = "cpu"
    ):
        self.nets = {name: nets[name].float().eval().to(device) for name in NETWORKS}
        self.running = {name: folded(net) for name, net in self.nets.items()}  # the calls'
        self.manifest = manifest
        self.device = torch.device(device)
        # names this prior in answers (Lifter.model_id): its manifest records the training's
        # settings, seconds and losses
        self.digest = hashlib.sha1(json.dumps(manifest, sort_keys=True).encode()).hexdigest()[:8]

    def to(self, device: str | torch.device) -> LiftingPrior:
        """A copy on `device` (this one's networks stay where they are)."""
        return LiftingPrior(copy.deepcopy(self.nets), self.manifest, device)

    @torch.inference_mode()
    def __call__(self, joints_2d: Tensor, visible: Tensor, intrinsics: Tensor | None) -> Tensor:
        """joints_2d: (B, 14, 2) px; visible: (B, 14) bool; intrinsics: (B, 3, 3) or None (weak
        perspective). Returns (B, 14, 3) mm, camera-oriented, root at the hip midpoint."""
        points, turn = query_view(joints_2d.float(), visible, intrinsics)
        features = prior_features(points, visible)
        nets = self.running
        noisy_share = (nets["noise"](features) / NOISE_GATE).clamp(0, 1)
        noisy_share = noisy_share.masked_fill(~visible.all(-1, keepdim=True), 1)[..., None]
        clean = lifted(nets["clean"], features)
        pose = clean + noisy_share * (lifted(nets["noisy"], features) - clean)
        if turn is not None:  # back from the turned camera: X = Q^T X'
            pose = pose @ turn
        return pose - hip_midpoint(pose)[:, None]

    def save(self, directory: Path) -> None:
        """`directory`/prior.pt (the shapes, the weights as `packed`) and manifest.json."""
        directory.mkdir(parents=True, exist_ok=True)
        saved = {
            name: {"shape": asdict(net.shape), "state": packed(net.state_dict())}
            for name, net in self.nets.items()
        }
        torch.save(saved, directory / "prior.pt")
        (directory / "manifest.json").write_text(json.dumps(self.manifest, indent=2) + "\n")

    @classmethod
    def load(cls, directory: Path, device: str | torch.device = "cpu") -> LiftingPrior:
        """The prior saved in `directory`. Raises DataFormatError."""
        try:
            saved = torch.load(directory / "prior.pt", weights_only=True)
            manifest = json.loads((directory / "manifest.json").read_text())
            nets = {}
            for name in NETWORKS:
                nets[name] = ResidualMLP(PriorShape(**saved[name]["shape"]))
                nets[name].load_state_dict(unpacked(saved[name]["state"]))
        except (OSError, ValueError, KeyError, TypeError, RuntimeError) as err:
            raise DataFormatError(f"{directory}: not a lifting prior ({err})") from err
        return cls(nets, manifest, device)


SCALE_SUFFIX = ".int8_scale"
# The hidden layers' weight matrices (of at least PACKED_SIDE rows and columns) are stored as int8;
# the first and the last layer's, which carry the input and the answer (the pose in mm), as
# float16: on S9 int8 everywhere cost 0.3 mm and 5 mm of root position, int8 in the hidden
# layers alone nothing (docs/tuning.md).
PACKED_SIDE = 256


def packed(state: dict[str, Tensor]) -> dict[str, Tensor]:
    """A network's state as stored, at about a quarter of float32's bytes: each hidden weight
    matrix (PACKED_SIDE) as int8 with one float32 scale per row (`name` + SCALE_SUFFIX; an
    element is off by at most half its row's scale, 1/254 of the row's largest magnitude), other
    floats as float16."""
    out = {}
    for name, value in state.items():
        if value.is_floating_point() and value.dim() == 2 and min(value.shape) >= PACKED_SIDE:
            scale = value.abs().amax(1, keepdim=True).clamp_min(1e-12) / 127
            out[name] = (value / scale).round().to(torch.int8)
            out[name + SCALE_SUFFIX] = scale
        else:
            out[name] = value.half() if value.is_floating_point() else value
    return out


def unpacked(stored: dict[str, Tensor]) -> dict[str, Tensor]:
    """The float32 state of a `packed` one."""
    out = {}
    for name, value in stored.items():
        if name.endswith(SCALE_SUFFIX):
            continue
        scale = stored.get(name + SCALE_SUFFIX)
        if scale is not None:
            out[name] = value.float() * scale
        else:
            out[name] = value.float() if value.is_floating_point() else value
    return out
