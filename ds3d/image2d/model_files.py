"""A trained 2D model on disk, and the one owner of its manifest format.

A model directory holds manifest.json and the files it names: one gzip-compressed forest per
cascade layer (forest1.pt.gz, ...), the PSM's mixtures (psm.pt), and the joint network
(jointnet.pt; its int8 copy for the people search, jointnet_int8.onnx, ds3d.image2d.quantized)
and/or the facing CNN (facing.pt). The manifest records the parameters (EstimatorParams,
flat), the training configuration and seed, the data and its terms, the training time and the
measured metrics.
"""

from __future__ import annotations

import gzip
import io
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, cast

import torch

from ds3d.errors import DataFormatError
from ds3d.image2d.facing import FacingNet
from ds3d.image2d.forest import Forest
from ds3d.image2d.jointnet import CPU_BFLOAT16, JointNet, JointNetShape, fold_batch_norms
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.psm import PairwiseMixtures
from ds3d.image2d.quantized import Int8JointNet, int8_available

NET_FILES = {"facing": "facing.pt", "jointnet": "jointnet.pt"}
PSM_FILE = "psm.pt"
INT8_FILE = "jointnet_int8.onnx"


@dataclass
class Model2D:
    """The parts of a trained 2D model: the cascade's layers, the PSM's mixtures, the
    parameters, and the networks it has (None where it has not; the int8 joint network also
    where this machine would not run it faster, quantized.int8_available)."""

    layers: list[Forest]
    mixtures: PairwiseMixtures
    params: EstimatorParams
    facing: FacingNet | None = None
    jointnet: JointNet | None = None
    jointnet_int8: Int8JointNet | None = None


def load_model(model_dir: Path, int8: bool = True) -> Model2D:
    """The model in `model_dir`; int8: with its int8 joint network where it has one (False:
    without, to quantize the float one anew). Raises DataFormatError when it is missing or
    malformed."""
    manifest = read_manifest(model_dir)
    try:
        params = EstimatorParams(**manifest["params"])
        layers = [load_forest(model_dir / name) for name in manifest["layers"]]
        state = torch.load(model_dir / manifest["psm"], weights_only=True)
        mixtures = PairwiseMixtures.from_state_dict(state)
        facing = manifest.get("facing")
        facing = load_facing(model_dir / facing) if facing else None
        jointnet, int8_file = manifest.get("jointnet"), manifest.get("jointnet_int8")
        if jointnet:
            shape = manifest["jointnet_shape"]
            shape = JointNetShape(tuple(shape["widths"]), tuple(shape["blocks"]))
            jointnet = load_jointnet(model_dir / jointnet, shape)
        quantized = None
        # (A copy in torch's int8 format, jointnet_int8.pt, is not read: the float network
        # runs until `ds3d quantize-jointnet` makes the ONNX one.)
        if int8 and int8_file == INT8_FILE and jointnet and int8_available():
            quantized = Int8JointNet((model_dir / int8_file).read_bytes())
    except (KeyError, TypeError, OSError, RuntimeError) as exc:
        raise DataFormatError(f"bad 2D model in {model_dir}: {exc}") from exc
    return Model2D(layers, mixtures, params, facing, jointnet, quantized)


def save_model(
    out_dir: Path,
    layers: list[Forest],
    mixtures: PairwiseMixtures,
    networks: dict[str, dict],
    params: EstimatorParams,
    provenance: dict,
    train_seconds: dict[str, float],
    jointnet_shape: JointNetShape | None = None,
) -> dict:
    """Write a trained model to out_dir (created): the layers, the mixtures, each network's
    state dict (networks: name in NET_FILES -> state dict) and the manifest, whose
    `provenance` entries (data, seed, train_config) are the trainer's to give, as are the
    seconds each part took to train and the joint network's shape. Returns the manifest."""
    out_dir.mkdir(parents=True, exist_ok=True)
    layer_files = [f"forest{i + 1}.pt.gz" for i in range(len(layers))]
    for forest, layer_file in zip(layers, layer_files, strict=True):
        save_forest(forest, out_dir / layer_file)
    for name, state in networks.items():
        torch.save(state, out_dir / NET_FILES[name])
    torch.save(mixtures.state_dict(), out_dir / PSM_FILE)
    manifest = {
        "model": "ds3d 2D pose: forest cascade unaries + pictorial structure model",
        **provenance,
        "params": asdict(params),
        "layers": layer_files,
        "psm": PSM_FILE,
        **{name: NET_FILES[name] if name in networks else None for name in NET_FILES},
        "jointnet_shape": None if jointnet_shape is None else asdict(jointnet_shape),
        "train_seconds": {k: round(v, 1) for k, v in train_seconds.items()},
        "metrics": {},
    }
    write_manifest(out_dir, manifest)
    return manifest


def replace_jointnet(
    model_dir: Path, state: dict, shape: JointNetShape, train_config: dict, seconds: float
) -> dict:
    """Put a (re)trained joint network into a model: its state dict and shape, the training
    configuration it was trained with, and the seconds it took. Returns the manifest."""
    manifest = read_manifest(model_dir)
    torch.save(state, model_dir / NET_FILES["jointnet"])
    manifest["jointnet"] = NET_FILES["jointnet"]
    manifest["jointnet_int8"] = None  # made of the network replaced: quantize the new one
    manifest["jointnet_shape"] = asdict(shape)
    manifest["train_config"] = train_config
    manifest["train_seconds"]["jointnet"] = round(seconds, 1)
    write_manifest(model_dir, manifest)
    return manifest


def save_int8_jointnet(model_dir: Path, quantized: bytes, calibration: dict) -> dict:
    """Put the int8 copy of a model's joint network (an ONNX model, ds3d.image2d.quantized) into
    it, with what it was calibrated on. Returns the manifest."""
    manifest = read_manifest(model_dir)
    (model_dir / INT8_FILE).write_bytes(quantized)
    manifest["jointnet_int8"] = INT8_FILE
    manifest["jointnet_int8_calibration"] = calibration
    write_manifest(model_dir, manifest)
    return manifest


def record_metrics(model_dir: Path, key: str, metrics: dict) -> dict:
    """Store measured metrics under manifest["metrics"][key]. Returns the manifest."""
    manifest = read_manifest(model_dir)
    manifest.setdefault("metrics", {})[key] = metrics
    write_manifest(model_dir, manifest)
    return manifest


def training_setup(model_dir: Path) -> tuple[dict, EstimatorParams]:
    """What a model was trained with: its training configuration (as saved) and parameters."""
    manifest = read_manifest(model_dir)
    return manifest["train_config"], EstimatorParams(**manifest["params"])


def save_forest(forest: Forest, path: Path) -> None:
    """Write a forest gzip-compressed (the tensors shrink ~2.5x, a 16-tree layer from 16 to 6 MB);
    the header's time is fixed so that the same forest always gives the same bytes."""
    with open(path, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as out:
        torch.save(forest.to_dict(), cast(IO[bytes], out))  # a GzipFile is a binary file


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


def load_jointnet(path: Path, shape: JointNetShape) -> JointNet:
    """The joint network's saved state dict (ds3d.image2d.jointnet) -> the network of `shape`,
    ready for inference (fold_batch_norms), in bfloat16 on a CPU that computes it
    (CPU_BFLOAT16): autocast would cast the weights again on every call, a fifth of the time;
    channels-last, as padded_logits feeds it."""
    net = JointNet(shape)
    net.load_state_dict(torch.load(path, weights_only=True))
    net = fold_batch_norms(net)
    # Module.to takes memory_format (as documented); torch's overloads of it leave it out.
    net = net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    return net.to(torch.bfloat16) if CPU_BFLOAT16 else net


def read_manifest(model_dir: Path) -> dict:
    path = Path(model_dir) / "manifest.json"
    if not path.is_file():
        raise DataFormatError(f"no manifest.json in {model_dir}")
    return json.loads(path.read_text())


def write_manifest(model_dir: Path, manifest: dict) -> None:
    (Path(model_dir) / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
