"""Exported graphs against PyTorch: both relation variants (the dynamic one at two object counts), the
detector, a deliberately diverging model that parity must catch, INT8, and the numpy decoding."""

import numpy as np
import pytest
import torch

from deepword.inference.decode import decode_couples, decode_owners
from deepword.inference.runtime import RELATION_OUTPUTS, ort_session
from deepword.relation_graph import ImageGraph, node_tensor
from stages.export.onnx_export import FoldedBackbone, export_detector, export_relation, relation_example
from stages.export.parity import ParityError, ParityReport, compare_detector, detector_parity, relation_parity
from stages.relation import decode as torch_decode
from stages.relation.model import ModelConfig, RelationNet
from tests.stages.export.tiny_models import CONV_FC_16, DETECTOR, RELATION_MODEL, RESNET18_16

torch.set_num_threads(1)


def trained_like(net: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """BatchNorm statistics and affine parameters as after training (fresh ones are the identity map,
    under which a wrong BatchNorm folding in the export would go unnoticed)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                c = m.num_features
                m.running_mean.copy_(torch.randn(c, generator=gen) * 0.5)
                m.running_var.copy_(torch.rand(c, generator=gen) + 0.5)
                m.weight.copy_(torch.rand(c, generator=gen) + 0.5)
                m.bias.copy_(torch.randn(c, generator=gen) * 0.2)
    return net.eval()


def small_net(seed: int = 0) -> RelationNet:
    torch.manual_seed(seed)
    return trained_like(RelationNet(ModelConfig(**RELATION_MODEL)), seed)


@pytest.mark.parametrize("backbone", [CONV_FC_16, RESNET18_16], ids=["conv_fc", "resnet18"])
def test_folded_backbone_computes_the_backbone_of_the_node_tensor(backbone):
    cfg = ModelConfig(**{**RELATION_MODEL, "backbone": backbone})
    torch.manual_seed(1)
    net = trained_like(RelationNet(cfg), seed=1)
    gen = torch.Generator().manual_seed(2)
    crops = torch.randint(0, 256, (5, 3, cfg.input_size, cfg.input_size), dtype=torch.uint8, generator=gen)
    coords = torch.rand((5, 4), generator=gen)
    with torch.no_grad():
        ref = net.backbone(node_tensor(crops, coords))
        folded = FoldedBackbone(net.backbone, cfg.input_size)(crops, coords)
    assert ref.abs().max() > 0.1
    torch.testing.assert_close(folded, ref, atol=1e-5, rtol=1e-5)


def test_dynamic_model_runs_the_backbone_on_real_objects_only(relation_models):
    import onnx

    _, static, dynamic = relation_models
    ops = {n.op_type for n in onnx.load(str(dynamic)).graph.node}
    assert "NonZero" in ops  # padded slots are skipped by gathering the real objects
    assert "NonZero" not in {n.op_type for n in onnx.load(str(static)).graph.node}  # static shapes throughout


def random_graphs(counts, size: int, seed: int = 0) -> list[ImageGraph]:
    """Graphs with ``counts`` nodes each: random crops, classes, priors and candidates."""
    rng = np.random.default_rng(seed)
    graphs = []
    for n in counts:
        classes = rng.integers(0, 2, n).astype(np.int8)
        cand = (classes[:, None] != classes[None, :]) | ((classes[:, None] == 1) & (classes[None, :] == 1))
        np.fill_diagonal(cand, False)
        adj = np.where(cand, rng.random((n, n)), 0).astype(np.float32)
        np.fill_diagonal(adj, 1.0)
        graphs.append(ImageGraph(crops=rng.integers(0, 256, (n, 3, size, size), dtype=np.uint8),
                                 coords=rng.random((n, 4), dtype=np.float32), classes=classes,
                                 valid=np.ones(n, bool), adj=adj, cand=cand))
    return graphs


@pytest.fixture(scope="module")
def relation_models(tmp_path_factory):
    out = tmp_path_factory.mktemp("relation_onnx")
    net = small_net()
    size = RELATION_MODEL["backbone"]["input_size"]
    static = export_relation(net, out / "static.onnx", size, 12, static=True)
    dynamic = export_relation(net, out / "dynamic.onnx", size, 12, static=False)
    return net, static, dynamic


def test_static_variant_matches_torch_padded_to_max_objects(relation_models):
    net, static, _ = relation_models
    size = RELATION_MODEL["backbone"]["input_size"]
    report = relation_parity(net, ort_session(static, 1), random_graphs([3, 12, 7], size), size, 0.5, n=12)
    report.check("static", 1e-4, 99.9)
    assert report.decisions > 50 and report.max_abs_diff < 1e-5


@pytest.mark.parametrize("counts", [[3, 2], [17, 9]])
def test_dynamic_variant_matches_torch_at_other_object_counts(relation_models, counts):
    net, _, dynamic = relation_models
    size = RELATION_MODEL["backbone"]["input_size"]
    report = relation_parity(net, ort_session(dynamic, 1), random_graphs(counts, size, seed=len(counts) + counts[0]),
                             size, 0.5, n=None)
    report.check("dynamic", 1e-4, 99.9)
    assert report.decisions > 0


def test_static_variant_refuses_another_object_count(relation_models):
    _, static, _ = relation_models
    feed = dict(zip(("crops", "coords", "adj", "cand"), (t.numpy() for t in relation_example(5, 16, 1)), strict=True))
    with pytest.raises(Exception, match="(?i)dimension|shape"):
        ort_session(static, 1).run(list(RELATION_OUTPUTS), feed)


def test_parity_catches_a_torch_model_that_diverges_after_export(relation_models):
    net, static, _ = relation_models
    size = RELATION_MODEL["backbone"]["input_size"]
    diverged = small_net()
    with torch.no_grad():  # one weight of the torch model changed after the ONNX file was written
        diverged.role_head.bias += 1.0
    report = relation_parity(diverged, ort_session(static, 1), random_graphs([6, 12], size), size, 0.5, n=12)
    assert report.max_abs_diff > 1e-2
    with pytest.raises(ParityError, match="differs from PyTorch"):
        report.check("static", 1e-4, 99.9)


def test_parity_catches_a_perturbed_onnx_graph(relation_models, tmp_path):
    import onnx
    from onnx import numpy_helper

    net, _, dynamic = relation_models
    model = onnx.load(str(dynamic))
    biggest = max(model.graph.initializer, key=lambda t: int(np.prod(t.dims)))  # the backbone's fc
    weights = numpy_helper.to_array(biggest)
    biggest.CopyFrom(numpy_helper.from_array(weights + 0.05 * np.sign(weights), biggest.name))
    onnx.save(model, str(tmp_path / "perturbed.onnx"))
    size = RELATION_MODEL["backbone"]["input_size"]
    report = relation_parity(net, ort_session(tmp_path / "perturbed.onnx", 1), random_graphs([5, 9], size), size,
                             0.5, n=None)
    with pytest.raises(ParityError):
        report.check("dynamic", 1e-4, 99.9)


def test_parity_catches_a_flipped_decision_even_within_the_tolerance():
    report = ParityReport()
    report.add(1e-6, agreeing=998, decisions=1000)
    with pytest.raises(ParityError):
        report.check("x", 1e-4, 99.9)


def test_detector_matches_torch_with_dynamic_batch_and_catches_divergence(tmp_path):
    from stages.detector.model import build_centernet, model_config

    torch.manual_seed(0)
    cfg = model_config(DETECTOR)
    net = build_centernet(cfg).eval()
    path = export_detector(net, tmp_path / "det.onnx", 64, 64, 10)
    images = np.random.default_rng(0).normal(size=(3, 3, 64, 64)).astype(np.float32)
    session = ort_session(path, 1)
    report = detector_parity(net, session, images, 10, 0.1, batch_size=3)  # traced at batch 2, run at 3
    report.check("detector", 1e-4, 99.9)
    with torch.no_grad():
        net.heads.wh[-1].bias += 1.0
    with pytest.raises(ParityError):
        detector_parity(net, session, images, 10, 0.1).check("detector", 1e-4, 99.9)


def test_int8_model_keeps_decisions_mostly(exported):
    _, metrics = exported
    assert metrics["export.relation.int8.parity_decision_agreement"] >= 90.0
    assert metrics["export.relation.int8.parity_max_abs_diff"] > 0  # it is a different (quantised) model


@pytest.mark.parametrize("one_owner,min_containment", [(True, 0.0), (False, 0.0), (True, 0.5), (False, 0.5)])
def test_numpy_decoding_equals_the_training_decoding(one_owner, min_containment):
    rng = np.random.default_rng(1)
    scores = rng.uniform(-1, 1, (4, 9, 9)).astype(np.float32)
    scores[:, :, 3] = scores[:, :, 4]  # ties: both pick the first
    classes = rng.integers(-1, 2, (4, 9))
    cand = (rng.random((4, 9, 9)) > 0.3).astype(np.float32)
    corner = rng.uniform(0, 0.7, (4, 9, 2))
    coords = np.concatenate([corner, corner + rng.uniform(0.05, 0.5, (4, 9, 2))], -1).astype(np.float32)
    t = [torch.from_numpy(a) for a in (scores, classes, cand)]
    numpy_owners = decode_owners(scores, classes, cand, 0.2, one_owner, coords, min_containment)
    np.testing.assert_array_equal(numpy_owners, torch_decode.decode_owners(
        *t, 0.2, one_owner, torch.from_numpy(coords), min_containment).numpy())
    if min_containment:  # the rule is active on these boxes
        assert numpy_owners.sum() < decode_owners(scores, classes, cand, 0.2, one_owner).sum()
    np.testing.assert_array_equal(decode_couples(scores, classes, cand, 0.2),
                                  torch_decode.decode_couples(*t, 0.2).numpy())


def test_detector_parity_is_relative_for_pixel_sizes_and_absolute_for_heatmap_and_offsets():
    heat = np.full((1, 2, 4, 4), 0.5, np.float32)
    size = np.full((1, 2, 4, 4), 120.0, np.float32)   # box sizes in pixels
    offset = np.full((1, 2, 4, 4), 0.25, np.float32)
    detections = np.zeros((1, 5, 6), np.float32)  # the decoded output: not compared (top-K order may differ)
    rounding = ParityReport()  # float32 rounding of a 120 px size: 2e-4 px, 1.7e-6 relative
    compare_detector(rounding, [heat, size, offset, detections], [heat, size + 2e-4, offset, detections + 1], 0.3)
    assert rounding.max_abs_diff < 1e-5
    rounding.check("detector", 1e-4, 99.9)
    drifted = ParityReport()  # the same 2e-4 on the heatmap is a real difference
    compare_detector(drifted, [heat, size, offset, detections], [heat + 2e-4, size, offset, detections], 0.3)
    with pytest.raises(ParityError, match="max \\|diff\\|"):
        drifted.check("detector", 1e-4, 99.9)


@pytest.mark.parametrize("static", [True, False])
def test_an_ensemble_exports_as_one_graph_averaging_its_members(tmp_path, static):
    from stages.relation.model import RelationEnsemble

    size = RELATION_MODEL["backbone"]["input_size"]
    members = [small_net(0), small_net(1)]
    ensemble = RelationEnsemble(members).eval()
    path = export_relation(ensemble, tmp_path / "ensemble.onnx", size, 12, static=static)
    graphs = random_graphs([5, 9], size, seed=4)
    report = relation_parity(ensemble, ort_session(path, 1), graphs, size, 0.5, n=12 if static else None)
    report.check("ensemble", 1e-4, 99.9)
    assert report.decisions > 0
    # the graph is the members' mean, not one member: member 0's own torch outputs disagree with it
    with pytest.raises(ParityError):
        relation_parity(members[0], ort_session(path, 1), graphs, size, 0.5, n=12 if static else None).check(
            "member 0", 1e-4, 99.9)


def test_a_detector_with_the_facing_head_exports_its_map_and_eight_column_detections(tmp_path):
    from deepword.inference.runtime import detector_outputs
    from stages.detector.model import build_centernet, model_config

    torch.manual_seed(0)
    net = build_centernet(model_config({**DETECTOR, "facing": True})).eval()
    path = export_detector(net, tmp_path / "det.onnx", 64, 64, 10)
    session = ort_session(path, 1)
    assert [o.name for o in session.get_outputs()] == list(detector_outputs(net.heads.regression, True))
    images = np.random.default_rng(0).normal(size=(2, 3, 64, 64)).astype(np.float32)
    (detections,) = session.run(["detections"], {"images": images})
    assert detections.shape == (2, 10, 8)
    detector_parity(net, session, images, 10, 0.1).check("detector", 1e-4, 99.9)   # the facing map compared too
