"""Adding a relation backbone is one module and one config node (docs/design.md §2): a backbone defined in this test
folder (``toy_backbone``), selected by ``relation/backbone=toy`` from a config folder of the test's own
(``toy_conf``, on Hydra's search path), trains in the relation stage on the smoke profile's settings, exports, and
its ONNX models keep parity with PyTorch, its input normalisation folded into its first convolution. A backbone
that does not declare its first convolution exports unfolded and says so."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from deepword.relation_graph import node_tensor
from tests.stages.export.tiny_models import EXPORT_CFG

REPO = Path(__file__).resolve().parents[3]
TOY_CONF = Path(__file__).resolve().parent / "toy_conf"


def compose_toy(*overrides: str):
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(REPO / "conf")):
            return compose("config", overrides=["profile=smoke", f"hydra.searchpath=[file://{TOY_CONF}]",
                                                "relation/backbone=toy", *overrides])
    finally:
        GlobalHydra.instance().clear()


def test_the_toy_backbone_composes_and_builds_from_its_node_alone():
    from stages.relation.model import ModelConfig, RelationNet
    from tests.stages.export.toy_backbone import ToyBackbone

    cfg = compose_toy()
    assert OmegaConf.to_container(cfg.relation.backbone) == {
        "_target_": "tests.stages.export.toy_backbone.ToyBackbone", "input_size": 24, "width": 6}
    net = RelationNet(ModelConfig.from_cfg(cfg.relation))
    assert isinstance(net.backbone, ToyBackbone) and net.backbone.fc.out_features == cfg.relation.model.hidden
    with pytest.raises(TypeError, match="does not take"):
        RelationNet(ModelConfig.from_cfg(compose_toy("+relation.backbone.expansion=4").relation))


@pytest.mark.slow
def test_a_toy_backbone_trains_exports_and_keeps_parity(upstream, tmp_path):
    from stages.export.stage import run as export
    from stages.relation.stage import load_network
    from stages.relation.stage import run as train

    cfg = compose_toy("relation.ensemble=1", "relation.model.hidden=16", "relation.model.embed_dim=8",
                      "relation.model.gat_hidden=8", "relation.max_objects=20", "relation.train.threads=1",
                      "relation.train.limit_train_images=null", "relation.train.limit_val_images=null", "seed=0")
    stage_cfg = OmegaConf.create({"relation": OmegaConf.to_container(cfg.relation, resolve=True),
                                  "trainer": OmegaConf.to_container(cfg.trainer, resolve=True), "seed": 0})
    relation = tmp_path / "relation"
    relation.mkdir()
    metrics = train(stage_cfg, {"data": upstream["data"], "priors": upstream["priors"]}, relation)
    assert metrics["relation.epochs"] == 1.0
    net, meta = load_network(relation)
    assert meta["model"]["backbone"]["_target_"] == "tests.stages.export.toy_backbone.ToyBackbone"
    assert type(net.backbone).__name__ == "ToyBackbone"

    out = tmp_path / "export"
    out.mkdir()
    torch.set_num_threads(1)
    exported = export(OmegaConf.create({"export": EXPORT_CFG, "seed": 0}),
                      {"data": upstream["data"], "priors": upstream["priors"], "relation": relation}, out)
    assert exported["export.relation.folded_first_conv"] == 1.0
    assert exported["export.relation.parity_max_abs_diff"] <= EXPORT_CFG["parity"]["max_abs_diff"]
    assert exported["export.relation.parity_decision_agreement"] >= EXPORT_CFG["parity"]["min_agreement"]
    assert exported["export.relation.parity_pairs"] > 0


def test_a_backbone_without_a_declared_first_convolution_exports_unfolded_and_says_so(tmp_path, caplog):
    import onnxruntime as ort

    from stages.export.onnx_export import (
        export_relation,
        folds_first_conv,
        relation_example,
        shipped_relation,
    )
    from stages.relation.model import ModelConfig, RelationNet

    def net_of(target: str) -> RelationNet:
        torch.manual_seed(0)
        spec = {"_target_": f"tests.stages.export.toy_backbone.{target}", "input_size": 16, "width": 4}
        return RelationNet(ModelConfig(backbone=spec, hidden=8, embed_dim=4, gat_hidden=4)).eval()

    declared, undeclared = net_of("ToyBackbone"), net_of("UndeclaredToyBackbone")
    assert folds_first_conv(declared) and not folds_first_conv(undeclared)
    with caplog.at_level(logging.WARNING, logger="stages.export.onnx_export"):
        shipped_relation(declared, real_only=False)
        assert not caplog.records
        shipped_relation(undeclared, real_only=False)
    assert any("does not declare its first convolution" in r.getMessage() and "UndeclaredToyBackbone" in r.getMessage()
               for r in caplog.records)
    # unfolded, it still computes what the network computes
    path = export_relation(undeclared, tmp_path / "relation.onnx", 16, 6, static=True)
    crops, coords, adj, cand = relation_example(6, 16)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"crops": crops.numpy(), "coords": coords.numpy(), "adj": adj.numpy(),
                             "cand": cand.numpy()})
    with torch.no_grad():
        want = undeclared(node_tensor(crops, coords), adj, cand)
    for g, w in zip(got, want, strict=True):
        assert abs(g - w.numpy()).max() < 1e-4
