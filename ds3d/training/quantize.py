"""The int8 copy of a 2D model's joint network for a CPU (ds3d.image2d.quantized), calibrated on
the network's inputs of training images: the search's levels and the 2D stage's crops (`ds3d
quantize-jointnet`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ds3d.boxes import person_boxes
from ds3d.data.lsp import PoseAnnotations, load_lsp
from ds3d.image2d.crops import resize_image, working_crops
from ds3d.image2d.features import lab_channels
from ds3d.image2d.jointnet import MARGIN, NET_BUCKET_STEPS, network_inputs
from ds3d.image2d.model_files import load_model, save_int8_jointnet
from ds3d.image2d.params import EstimatorParams
from ds3d.image2d.quantized import ENGINE, quantize_jointnet
from ds3d.io.images import read_image
from ds3d.people.search import SEARCH_BUCKET_STEPS, SearchParams, level_extents, level_inputs


def quantize_model(model_dir: Path, images: int) -> dict:
    """Quantize the joint network of the model in `model_dir` on LSP train's first `images`
    images (never held out: the held-out images start at im0701), as the search's levels and as
    the 2D stage's crops of their person at the working scale, and put it into the model.
    Returns the manifest."""
    if not 0 < images <= 700:
        raise ValueError(f"calibrate on 1 to 700 of LSP train's images, got {images}")
    model = load_model(Path(model_dir), int8=False)  # its float network, quantized anew
    if model.jointnet is None:
        raise ValueError(f"the model in {model_dir} has no joint network to quantize")
    ann = load_lsp(split="train").subset(range(images))
    pictures = [read_image(p) for p in ann.image_paths]
    cpu = torch.device("cpu")
    search = SearchParams()
    extents = [level_extents(picture.shape[0], search) for picture in pictures]
    _, levels, beyond = level_inputs(pictures, extents, model.params, search, cpu)
    crops = [
        lab_channels(torch.from_numpy(image)[None]) for image in _crops(pictures, ann, model.params)
    ]
    inputs = network_inputs(levels, beyond, SEARCH_BUCKET_STEPS)
    inputs += network_inputs(crops, MARGIN, NET_BUCKET_STEPS)
    quantized = quantize_jointnet(model.jointnet, inputs)
    calibration = {
        "engine": ENGINE,
        "images": f"LSP train im0001-im{images:04d}: the search's levels, the person's crop",
        "inputs": len(inputs),
    }
    return save_int8_jointnet(Path(model_dir), quantized, calibration)


def _crops(
    pictures: list[np.ndarray], ann: PoseAnnotations, params: EstimatorParams
) -> list[np.ndarray]:
    """Each image's crop around its annotated person, at the working scale (crops.working_crops
    of the person's box): (h, w, 3) uint8 RGB each."""
    boxes = person_boxes(ann.joints, ann.located)
    return [
        resize_image(crop.image, crop.base) for crop in working_crops(pictures, list(boxes), params)
    ]
