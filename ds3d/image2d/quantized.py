"""The joint network in 8-bit integers, for a CPU.

The joint network is most of a searched image's time: over the search's pyramid, then on each
crop. On a CPU without bfloat16 (AVX2, most servers and laptops) its convolutions run about 1.7
times faster in int8 (x86 backend: weights per channel, activations per tensor) than in float32,
at the same PCK on held-out images (docs/tuning.md, speed).

Post-training static quantization (torch.ao FX): the activations' ranges are observed on
calibration inputs of training images, the search's levels and the 2D stage's crops (`ds3d
quantize-jointnet`), and stored with the int8 weights in the model's jointnet_int8.pt. Loading
quantizes a copy of the float network's graph the same way and puts the stored numbers into it.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Iterable

import torch
from torch import Tensor, nn
from torch.fx import GraphModule

from ds3d.image2d.jointnet import CPU_BFLOAT16, JointNet

ENGINE = "x86"  # torch's quantized backend for x86 CPUs (fbgemm and oneDNN kernels)
# Left in float: the head, whose logits are the search's unaries as they are (no softmax to
# forgive their rounding). In int8 it cost the search 4 of 277 people on LSP train's held-out
# harder canvases against the float network; a float head finds them, at the same speed
# (docs/tuning.md, speed).
FLOAT_MODULES = ("head",)


def int8_available() -> bool:
    """Whether this machine computes the int8 network faster than the float one: an x86 CPU
    without bfloat16 (where bfloat16 runs, the float network already does, CPU_BFLOAT16)."""
    return ENGINE in torch.backends.quantized.supported_engines and not CPU_BFLOAT16


def quantize_jointnet(net: JointNet, inputs: Iterable[Tensor]) -> nn.Module:
    """The int8 network of a float one (on the CPU, batch norms folded) whose activations'
    ranges are those of `inputs`, the network's padded inputs (B, 3, H, W) channels-last."""
    torch.backends.quantized.engine = ENGINE
    observed = _prepared(net, next(iter(inputs)))
    with torch.no_grad():
        for x in inputs:
            observed(x)
    return _converted(observed)


def int8_jointnet(net: JointNet, state: dict) -> nn.Module:
    """The int8 network that quantize_jointnet made of `net`, from its state dict."""
    torch.backends.quantized.engine = ENGINE
    example = torch.zeros(1, 3, 64, 64).contiguous(memory_format=torch.channels_last)
    quantized = _converted(_prepared(net, example))
    with warnings.catch_warnings():  # torch.ao's notices of its own future
        warnings.simplefilter("ignore")
        quantized.load_state_dict(state)
    return quantized


def _prepared(net: JointNet, example: Tensor) -> GraphModule:
    """A copy of the float network traced and given observers (FX graph mode)."""
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import prepare_fx

    with warnings.catch_warnings():  # torch.ao's notices of its own future
        warnings.simplefilter("ignore")
        mapping = get_default_qconfig_mapping(ENGINE)
        for name in FLOAT_MODULES:
            mapping = mapping.set_module_name(name, None)
        return prepare_fx(copy.deepcopy(net).float().eval(), mapping, (example,))


def _converted(observed: GraphModule) -> nn.Module:
    """The int8 network of an observed one, marked so that the network's callers run it as it
    is (jointnet._run: float32 input on the CPU, no autocast)."""
    from torch.ao.quantization.quantize_fx import convert_fx

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        quantized = convert_fx(observed)
    setattr(quantized, "int8", True)  # noqa: B010 (an attribute nn.Module does not declare)
    return quantized.eval()
