"""The joint network in 8-bit integers, for a CPU, run by ONNX Runtime.

The joint network is most of a searched image's time: over the search's pyramid, then on each
crop. On a CPU without bfloat16 (AVX2, most servers and laptops) its convolutions run about 1.7
times faster in int8 than in float32, and ONNX Runtime's int8 kernels run this network about
1.3 times faster again than torch's own (docs/tuning.md, speed).

Post-training static quantization (onnxruntime.quantization, QDQ format): the float network is
exported to ONNX, the activations' ranges are observed on calibration inputs of training images,
the search's levels and the 2D stage's crops (`ds3d quantize-jointnet`), and the graph with its
int8 weights (per output channel, 7 bits) and uint8 activations (per tensor) is the model's
jointnet_int8.onnx. Making it needs the `onnx` package (the dev extra); running it, onnxruntime
alone.
"""

from __future__ import annotations

import copy
import importlib.util
import tempfile
import threading
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

from ds3d.errors import DataFormatError
from ds3d.image2d.jointnet import CPU_BFLOAT16, JointNet

if TYPE_CHECKING:
    import onnxruntime as ort

ENGINE = "onnxruntime"
# Left in float: the head, whose logits are the search's unaries as they are (no softmax to
# forgive their rounding). In int8 it cost the search 4 of 277 people on LSP train's held-out
# harder canvases against the float network; a float head finds them, at the same speed
# (docs/tuning.md, speed).
FLOAT_MODULES = ("head",)
_INPUT, _OUTPUT = "lab", "logits"


def int8_available() -> bool:
    """Whether this machine computes the int8 network faster than the float one: a CPU without
    bfloat16 (where bfloat16 runs, the float network already does, CPU_BFLOAT16), with
    onnxruntime installed (a dependency; a bare CUDA image may lack it, tools/gpu_check.py)."""
    return not CPU_BFLOAT16 and importlib.util.find_spec("onnxruntime") is not None


def quantize_jointnet(net: JointNet, inputs: Iterable[Tensor]) -> bytes:
    """The int8 network (an ONNX model, serialised) of a float one whose activations' ranges
    are those of `inputs`, the network's padded inputs (B, 3, H, W)."""
    try:
        from onnxruntime.quantization import (
            CalibrationDataReader,
            QuantFormat,
            QuantType,
            quantize_static,
        )
    except ModuleNotFoundError as exc:  # onnxruntime.quantization reads graphs with onnx
        raise ModuleNotFoundError(
            f"quantizing the joint network needs the onnx package (the dev extra): {exc}"
        ) from exc

    batches = [{_INPUT: x.float().contiguous().numpy()} for x in inputs]

    class Inputs(CalibrationDataReader):
        def __init__(self):
            self.left = iter(batches)

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.left, None)

    with tempfile.TemporaryDirectory() as tmp:
        exact, rounded = Path(tmp) / "float.onnx", Path(tmp) / "int8.onnx"
        _export(net, torch.from_numpy(batches[0][_INPUT]), exact)
        quantize_static(
            str(exact),
            str(rounded),
            Inputs(),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            # Weights in 7 bits: x86 CPUs without VNNI (AVX2) multiply uint8 by int8 in pairs
            # summed into int16, which 8-bit weights overflow; the overflow took 1.9 points of
            # recall on the held-out harder canvases (docs/tuning.md, speed).
            reduce_range=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            nodes_to_exclude=[f"/{name}/Conv" for name in FLOAT_MODULES],
        )
        return rounded.read_bytes()


def _export(net: JointNet, example: Tensor, path: Path) -> None:
    """The float network on the CPU as an ONNX graph of any batch and input size."""
    net = copy.deepcopy(net).float().eval()
    size = {0: "batch", 2: "height", 3: "width"}
    with warnings.catch_warnings():  # torch.onnx's notices of its own future
        warnings.simplefilter("ignore")
        torch.onnx.export(
            net,
            (example.float().contiguous(),),  # the weights' memory format is the input's
            str(path),
            input_names=[_INPUT],
            output_names=[_OUTPUT],
            dynamic_axes={_INPUT: size, _OUTPUT: size},
            dynamo=False,
        )


class Int8JointNet(nn.Module):
    """The int8 network of quantize_jointnet, run by ONNX Runtime on the CPU: (B, 3, H, W)
    float32 Lab / 100 -> (B, 14, ceil(H / 4), ceil(W / 4)) float32 logits, as JointNet. It
    runs on torch.get_num_threads() threads of its caller, as a torch op would: one session
    per thread count (a batch split over threads of one intra-op thread each,
    ds3d.util.threads, runs one-thread sessions side by side)."""

    int8 = True  # jointnet._run hands it its input as it is

    def __init__(self, model: bytes):
        """model: the serialised ONNX model; DataFormatError where ONNX Runtime cannot read it
        (a session is made at once, for the calling thread's count)."""
        super().__init__()
        self.model = model
        self._sessions: dict[int, ort.InferenceSession] = {}
        self._lock = threading.Lock()
        self._session(torch.get_num_threads())

    def forward(self, lab: Tensor) -> Tensor:
        session = self._session(torch.get_num_threads())
        x = lab.float().contiguous().cpu().numpy()
        return torch.from_numpy(session.run(None, {_INPUT: x})[0])

    def _session(self, threads: int) -> ort.InferenceSession:
        with self._lock:
            if threads not in self._sessions:
                import onnxruntime as ort

                options = ort.SessionOptions()
                options.intra_op_num_threads = threads
                options.inter_op_num_threads = 1
                # Threads that wait for work sleep: the forests and PSMs on the other threads
                # need the cores between the network's calls.
                options.add_session_config_entry("session.intra_op.allow_spinning", "0")
                try:
                    self._sessions[threads] = ort.InferenceSession(
                        self.model, options, providers=["CPUExecutionProvider"]
                    )
                except Exception as exc:  # onnxruntime's errors derive from Exception alone
                    raise DataFormatError(f"not a readable ONNX model: {exc}") from exc
            return self._sessions[threads]
