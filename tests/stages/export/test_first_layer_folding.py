"""The coordinate planes' share of the first convolution as a 2x2 convolution on a grid (``corner_kernel``),
and onnxruntime running it inside the RGB convolution once the export names the object dimension."""

import numpy as np
import onnx
import pytest
import torch
import torch.nn.functional as F

from deepword.inference.runtime import ort_session
from deepword.relation_graph import node_tensor
from stages.export.onnx_export import (
    FoldedBackbone,
    corner_kernel,
    export_relation,
    grid_mask,
    name_object_dims,
    plane_grid,
    plane_responses,
)
from stages.relation.backbone_spec import CONV_FC, RESNET18
from stages.relation.model import ModelConfig, RelationNet

torch.set_num_threads(1)
DEFAULT_NET = ModelConfig(backbone={"_target_": CONV_FC, "input_size": 56, "expansion": 4}, hidden=128, embed_dim=64,
                          gat=True,
                          gat_hidden=64, edge_geometry=True, geometry_gate=True)


@pytest.mark.parametrize("size,kernel,stride,padding", [(56, 3, 2, 1), (28, 3, 2, 1), (16, 3, 2, 1), (8, 3, 2, 1)])
def test_corner_kernel_reproduces_the_planes_response_exactly(size, kernel, stride, padding):
    torch.manual_seed(0)
    weight = torch.randn(6, 4, kernel, kernel)
    responses = plane_responses(weight, size, stride, padding)
    k = corner_kernel(responses)
    assert k is not None and k.shape == (6, 4, 2, 2)
    coords = torch.rand(3, 4, dtype=torch.float64)
    planes = coords[..., None, None].expand(3, 4, size, size)
    expected = F.conv2d(planes, weight.double(), None, stride, padding)
    got = F.conv2d(plane_grid(coords, grid_mask(responses.shape[-2:], torch.float64)), k)
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("size,kernel,stride,padding", [(28, 7, 2, 3), (57, 3, 2, 1), (7, 3, 2, 1), (16, 3, 1, 1)])
def test_corner_kernel_declines_geometries_with_more_border_values(size, kernel, stride, padding):
    weight = torch.randn(6, 4, kernel, kernel, generator=torch.Generator().manual_seed(0))
    assert corner_kernel(plane_responses(weight, size, stride, padding)) is None


@pytest.mark.parametrize("backbone,on_grid", [({"_target_": CONV_FC, "input_size": 28, "expansion": 1}, True),
                                               ({"_target_": RESNET18, "input_size": 28, "base_width": 8}, False)],
                         ids=["conv_fc", "resnet18"])
def test_folded_backbone_uses_the_grid_where_it_is_exact(backbone, on_grid):
    cfg = ModelConfig(backbone=backbone, hidden=16)
    torch.manual_seed(3)
    net = RelationNet(cfg).eval()
    folded = FoldedBackbone(net.backbone, cfg.input_size)
    assert folded.on_grid is on_grid
    crops = torch.randint(0, 256, (4, 3, 28, 28), dtype=torch.uint8, generator=torch.Generator().manual_seed(4))
    coords = torch.rand(4, 4, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        torch.testing.assert_close(folded(crops, coords), net.backbone(node_tensor(crops, coords)),
                                   atol=1e-5, rtol=1e-5)


def blocked_convs(optimized: onnx.ModelProto) -> list[onnx.NodeProto]:
    return [n for n in optimized.graph.node if n.op_type == "Conv" and n.domain == "com.microsoft.nchwc"]


def sums_inside(conv: onnx.NodeProto) -> bool:
    """An onnxruntime blocked convolution that adds its 4th input and applies a ReLU in its kernel."""
    activation = {a.name: a.s for a in conv.attribute}.get("activation")
    return len(conv.input) == 4 and activation == b"Relu"


def optimized_graph(path, tmp_path) -> onnx.ModelProto:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.optimized_model_filepath = str(tmp_path / "optimized.onnx")
    ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return onnx.load(options.optimized_model_filepath)


@pytest.fixture(scope="module")
def default_net():
    torch.manual_seed(0)
    return RelationNet(DEFAULT_NET).eval()


@pytest.mark.parametrize("static", [False, True])
def test_onnxruntime_runs_the_plane_convolution_inside_the_rgb_convolution(default_net, static, tmp_path):
    path = export_relation(default_net, tmp_path / "relation.onnx", 56, 24, static=static)
    convs = blocked_convs(optimized_graph(path, tmp_path))
    if not convs:
        pytest.skip("this CPU has no blocked (NCHWc) convolution kernels in onnxruntime")
    assert sum(sums_inside(c) for c in convs) == 1  # the RGB convolution adds the planes' and applies the ReLU
    # without the names (the tracer's annotations alone) the add and the ReLU stay outside: the test sees it
    unnamed = onnx.load(str(path))
    del unnamed.graph.value_info[:]
    onnx.save(unnamed, str(tmp_path / "unnamed.onnx"))
    assert not any(sums_inside(c) for c in blocked_convs(optimized_graph(tmp_path / "unnamed.onnx", tmp_path)))


def test_named_model_still_matches_torch_with_padded_slots(default_net, tmp_path):
    path = export_relation(default_net, tmp_path / "relation.onnx", 56, 24, static=False)
    gen = torch.Generator().manual_seed(1)
    crops = torch.randint(0, 256, (2, 9, 3, 56, 56), dtype=torch.uint8, generator=gen)
    coords = torch.rand((2, 9, 4), generator=gen)
    coords[1, 6:] = 0  # padded slots: all-zero boxes
    valid = (coords.abs().sum(-1) > 0).float()
    adj = torch.rand((2, 9, 9), generator=gen) * valid[:, :, None] * valid[:, None, :]
    cand = torch.ones(2, 9, 9) * valid[:, :, None] * valid[:, None, :]
    feed = {"crops": crops.numpy(), "coords": coords.numpy(), "adj": adj.numpy(), "cand": cand.numpy()}
    got = ort_session(path, threads=1).run(None, feed)
    with torch.no_grad():
        ref = default_net(node_tensor(crops, coords), adj, cand)
    real = valid.numpy() > 0  # padded slots' front probability is not an output that counts (parity masks it)
    np.testing.assert_allclose(got[0], ref[0].numpy(), atol=1e-4)
    np.testing.assert_allclose(got[1], ref[1].numpy(), atol=1e-4)
    np.testing.assert_allclose(got[2][real], ref[2].numpy()[real], atol=1e-4)


def test_name_object_dims_gives_both_first_convolutions_one_object_dimension(default_net, tmp_path):
    model = onnx.load(str(export_relation(default_net, tmp_path / "relation.onnx", 56, 24, static=False)))
    unnamed = onnx.ModelProto()
    unnamed.CopyFrom(model)
    del unnamed.graph.value_info[:]
    named = name_object_dims(unnamed)
    assert [n.op_type for n in named.graph.node] == [n.op_type for n in unnamed.graph.node]  # shapes only
    shapes = {v.name: v.type.tensor_type.shape.dim for v in named.graph.value_info}
    first = [n.output[0] for n in named.graph.node if n.op_type == "Conv"][:2]  # the grid and the RGB convolution
    dims = [shapes[name][0].dim_param for name in first]
    assert dims[0] and dims[0] == dims[1], dims
