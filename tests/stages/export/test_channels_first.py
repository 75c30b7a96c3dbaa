"""ChannelsFirstGraph: the graph part of RelationNet with channels-first pair tensors computes what
``RelationNet.relate`` computes, for every combination of the GAT and the two geometry additions, in
PyTorch and exported to ONNX at two object counts."""

import itertools
import warnings

import pytest
import torch

from deepword.inference.runtime import ort_session
from stages.export.channels_first import ChannelsFirstGraph, pair_geometry_channels_first
from stages.relation.backbone_spec import CONV_FC
from stages.relation.model import ModelConfig, RelationNet, pair_geometry

torch.set_num_threads(1)

HIDDEN = 16


def _net(gat: bool = True, edge_geometry: bool = True, geometry_gate: bool = True) -> RelationNet:
    torch.manual_seed(0)
    cfg = ModelConfig(backbone={"_target_": CONV_FC, "input_size": 8, "expansion": 1}, hidden=HIDDEN, embed_dim=8, gat=gat,
                      gat_hidden=8, edge_geometry=edge_geometry, geometry_gate=geometry_gate)
    return RelationNet(cfg).eval()


def _inputs(batch: int, n: int, seed: int = 1):
    """h, adj, cand, coords as the export stage passes them: the last objects of image 0 and 1 are
    padding (all-zero boxes, zero features, no edges, not candidates); valid nodes have self-loops."""
    gen = torch.Generator().manual_seed(seed)
    h = torch.randn(batch, n, HIDDEN, generator=gen)
    adj = torch.rand(batch, n, n, generator=gen) * (torch.rand(batch, n, n, generator=gen) > 0.4)
    adj = adj + torch.eye(n)
    cand = (torch.rand(batch, n, n, generator=gen) > 0.5).float()
    top_left = torch.rand(batch, n, 2, generator=gen) * 0.7
    coords = torch.cat([top_left, top_left + 0.02 + torch.rand(batch, n, 2, generator=gen) * 0.3], -1)
    for b, k in ((0, n - 2), (1, n - 3)):
        h[b, k:], coords[b, k:], adj[b, k:], adj[b, :, k:], cand[b, k:], cand[b, :, k:] = 0, 0, 0, 0, 0, 0
    return h, adj, cand, coords


def _assert_outputs_close(got, ref):
    assert len(got) == len(ref) == 3
    for g, r in zip(got, ref, strict=True):
        assert tuple(g.shape) == tuple(r.shape)
        torch.testing.assert_close(torch.as_tensor(g), r, atol=1e-5, rtol=0)


@pytest.mark.parametrize("gat,edge_geometry,geometry_gate", list(itertools.product([False, True], repeat=3)))
def test_channels_first_graph_computes_relate(gat, edge_geometry, geometry_gate):
    net = _net(gat, edge_geometry, geometry_gate)
    graph = ChannelsFirstGraph(net)
    assert len(list(graph.parameters())) == len(list(net.parameters()))  # shares, copies nothing
    h, adj, cand, coords = _inputs(3, 9)
    with torch.no_grad():
        ref = net.relate(h, adj, cand, coords)
        got = graph(h, adj, cand, coords)
    assert ref[0].abs().max() > 0.05 and ref[1].abs().max() > 0.05
    _assert_outputs_close(got, ref)


def test_pair_geometry_channels_first_is_pair_geometry_permuted():
    _, _, _, coords = _inputs(3, 11)
    ref = pair_geometry(coords).permute(0, 3, 1, 2)
    got = pair_geometry_channels_first(coords)
    assert got.shape == (3, 8, 11, 11)
    torch.testing.assert_close(got, ref, atol=1e-7, rtol=0)


def test_missing_coords_raise_like_relate():
    net = _net(gat=True, edge_geometry=False, geometry_gate=True)
    h, adj, cand, _ = _inputs(2, 5)
    with pytest.raises(ValueError, match="coords"):
        net.relate(h, adj, cand)
    with pytest.raises(ValueError, match="coords"):
        ChannelsFirstGraph(net)(h, adj, cand)
    plain = _net(gat=True, edge_geometry=False, geometry_gate=False)  # no geometry needed: no coords needed
    with torch.no_grad():
        _assert_outputs_close(ChannelsFirstGraph(plain)(h, adj, cand), plain.relate(h, adj, cand))


def test_exported_channels_first_graph_matches_relate_at_two_object_counts(tmp_path):
    net = _net()
    graph = ChannelsFirstGraph(net).eval()
    path = tmp_path / "graph.onnx"
    names = ["h", "adj", "cand", "coords"]
    axes = {"h": {0: "batch", 1: "objects"}, "coords": {0: "batch", 1: "objects"}, "front": {0: "batch", 1: "objects"},
            **{name: {0: "batch", 1: "objects", 2: "objects"} for name in ("adj", "cand", "owner", "couple")}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, _inputs(2, 7), str(path), dynamo=False, opset_version=17,
                          do_constant_folding=True, input_names=names, output_names=["owner", "couple", "front"],
                          dynamic_axes=axes)
    session = ort_session(path, threads=1)
    for batch, n in ((3, 5), (2, 12)):
        inputs = _inputs(batch, n, seed=n)
        with torch.no_grad():
            ref = net.relate(*inputs)
        got = session.run(None, {name: t.numpy() for name, t in zip(names, inputs, strict=True)})
        _assert_outputs_close([torch.from_numpy(g) for g in got], ref)
