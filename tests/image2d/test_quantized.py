"""The joint network in int8 for a CPU (ds3d.image2d.quantized): made, stored in its model, read
back the same, and close to the float network it was made of."""

import json
import shutil

import onnx
import pytest
import torch

from ds3d.errors import DataFormatError
from ds3d.image2d.estimator import PoseEstimator2D
from ds3d.image2d.jointnet import JointNet, JointNetShape, fold_batch_norms, padded_logits
from ds3d.image2d.model_files import INT8_FILE, replace_jointnet, save_int8_jointnet
from ds3d.image2d.quantized import Int8JointNet, int8_available, quantize_jointnet
from ds3d.util.threads import intra_op_threads

pytestmark = pytest.mark.skipif(not int8_available(), reason="no int8 engine for this CPU")


def _images(count: int, seed: int = 0) -> list[torch.Tensor]:
    """Smooth random Lab-like images (B, 3, H, W) channels-last: structure for the network."""
    generator = torch.Generator().manual_seed(seed)
    out = []
    for k in range(count):
        coarse = torch.rand(1, 3, 6 + k % 3, 5 + k % 2, generator=generator)
        image = torch.nn.functional.interpolate(coarse, size=(96, 80), mode="bilinear")
        out.append(image.contiguous(memory_format=torch.channels_last))
    return out


def _net() -> JointNet:
    torch.manual_seed(0)
    net = JointNet(JointNetShape((16, 24, 32), (1, 1, 1)))
    for module in net.modules():  # batch norms with statistics of their own, as trained
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.1, 0.1)
            module.running_var.uniform_(0.5, 2.0)
    return fold_batch_norms(net)


def test_the_int8_network_answers_close_to_the_float_one_and_reads_back_the_same():
    net = _net()
    model = quantize_jointnet(net, _images(8))
    quantized = Int8JointNet(model)
    image = _images(1, seed=7)[0]
    with torch.no_grad():
        exact, rounded = net(image), quantized(image)
    assert rounded.shape == exact.shape and rounded.dtype == torch.float32
    # int8 rounds each layer's activations to 1/255 of its observed range: the logits follow
    # the float ones closely, far from noise
    correlation = torch.corrcoef(torch.stack([exact.flatten(), rounded.flatten()]))[0, 1]
    assert correlation > 0.95
    # the head stays in float: its logits are the search's unaries, not rounded to int8 steps
    # (no QuantizeLinear after the head's Conv, which writes the output)
    graph = onnx.load_from_string(model).graph
    writers = {out: node.op_type for node in graph.node for out in node.output}
    assert writers["logits"] == "Conv"
    assert {"QuantizeLinear", "DequantizeLinear"} <= set(writers.values())
    # the same bytes read back give the same logits, on one thread or two
    again = Int8JointNet(model)
    with torch.no_grad():
        torch.testing.assert_close(again(image), rounded)
        with intra_op_threads(2):
            torch.testing.assert_close(again(image), rounded)
    # padded_logits runs it as the float network is run, on float32 input, without autocast
    lab = image.contiguous()
    assert padded_logits(again, lab).shape == padded_logits(net, lab).shape


def test_a_model_runs_its_int8_network_until_the_network_is_replaced(small_model, tmp_path):
    model = tmp_path / "image2d"
    shutil.copytree(small_model, model)
    estimator = PoseEstimator2D.load(model)
    assert estimator.jointnet is not None and estimator.network is estimator.jointnet
    quantized = quantize_jointnet(estimator.jointnet, _images(4))
    save_int8_jointnet(model, quantized, {"inputs": 4})
    loaded = PoseEstimator2D.load(model)
    assert loaded.network is loaded.jointnet_int8 is not None
    assert loaded.to("cpu").network is loaded.jointnet_int8  # a GPU would get the float one
    manifest = json.loads((model / "manifest.json").read_text())
    assert manifest["jointnet_int8"] == INT8_FILE
    state = torch.load(small_model / "jointnet.pt", weights_only=True)
    shape = JointNetShape(**manifest["jointnet_shape"])
    replace_jointnet(model, state, shape, manifest["train_config"], 1.0)
    assert PoseEstimator2D.load(model).network is not None
    assert PoseEstimator2D.load(model).jointnet_int8 is None  # made of the network replaced


def test_a_model_is_quantized_anew_from_its_float_network(small_model, tmp_path):
    """`ds3d quantize-jointnet` on a model that has an int8 network already quantizes its float
    one again."""
    from ds3d.training.quantize import quantize_model

    model = tmp_path / "image2d"
    shutil.copytree(small_model, model)
    for _ in range(2):
        manifest = quantize_model(model, images=2)
        assert manifest["jointnet_int8"] == INT8_FILE
    loaded = PoseEstimator2D.load(model)
    assert loaded.jointnet_int8 is not None and loaded.network is loaded.jointnet_int8


def test_a_model_with_an_int8_copy_of_another_format_runs_its_float_network(small_model, tmp_path):
    """A model quantized by torch (jointnet_int8.pt) runs its float network until `ds3d
    quantize-jointnet` makes the ONNX copy; an unreadable ONNX copy is refused at load."""
    model = tmp_path / "image2d"
    shutil.copytree(small_model, model)
    manifest = json.loads((model / "manifest.json").read_text())
    (model / "jointnet_int8.pt").write_bytes(b"torch's int8 state")
    manifest["jointnet_int8"] = "jointnet_int8.pt"
    (model / "manifest.json").write_text(json.dumps(manifest))
    loaded = PoseEstimator2D.load(model)
    assert loaded.jointnet_int8 is None and loaded.network is loaded.jointnet
    (model / INT8_FILE).write_bytes(b"not a graph")
    manifest["jointnet_int8"] = INT8_FILE
    (model / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataFormatError, match="ONNX"):
        PoseEstimator2D.load(model)
