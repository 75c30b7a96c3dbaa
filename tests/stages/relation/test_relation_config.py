"""The relation config groups compose on the real conf/: each ablation changes exactly the field it
names, and every backbone option builds a network of its input size."""

import functools
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from deepword.relation_graph import InputConfig
from stages.relation.model import ModelConfig, RelationNet, count_parameters, size_mb

CONF = Path(__file__).resolve().parents[3] / "conf"
ABLATIONS = {
    "none": {},
    "neg0.1": {"relation.loss.neg_weight": 0.1},
    "fewer_neg": {"relation.min_prior": 0.05},
    "small_mask": {"relation.small_mask_px": 8},
    "input56": {"relation.backbone.input_size": 56},
    "ex4": {"relation.backbone.expansion": 4},
    "no_gat": {"relation.model.gat": False},
    "no_edge_geometry": {"relation.model.edge_geometry": False},
    "no_prior": {"relation.adjacency": "uniform"},
    "no_containment": {"relation.decode.min_containment": 0.0},
    "no_geometry_gate": {"relation.model.geometry_gate": False},
    "no_rank": {"relation.loss.rank_weight": 0.0},
    "no_min_crop": {"relation.min_crop_px": 0},
}


def _compose(*overrides: str):
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            return compose(config_name="config", overrides=list(overrides))
    finally:
        GlobalHydra.instance().clear()


def _leaves(cfg) -> dict:
    out = {}

    def walk(node, prefix):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}.{k}" if prefix else k)
        else:
            out[prefix] = node

    walk(OmegaConf.to_container(cfg, resolve=False), "")
    return out


def test_every_ablation_option_exists():
    assert {p.stem for p in (CONF / "ablation").glob("*.yaml")} == set(ABLATIONS)


@functools.cache
def _conv_fc_leaves() -> dict:
    return _leaves(_compose("relation/backbone=conv_fc"))


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_ablation_changes_only_its_field(name):
    # on conv_fc (28 px, expansion 1), where input56 and ex4 are not no-ops as on the default backbone
    base = _conv_fc_leaves()
    ablated = _leaves(_compose("relation/backbone=conv_fc", f"ablation={name}"))
    changed = {k: ablated[k] for k in base.keys() | ablated.keys() if base.get(k, "<absent>") != ablated.get(k, "<absent>")}
    assert changed == ABLATIONS[name]


def test_default_relation_config_and_stage_declaration():
    cfg = _compose()
    assert cfg.relation.backbone._target_ == "stages.relation.backbones.ConvFC" and cfg.relation.backbone.input_size == 56
    assert cfg.relation.backbone.expansion == 4 and cfg.relation.decode.one_owner is True
    stage = cfg.pipeline.stages.relation
    assert stage.run == "stages.relation.stage:run" and list(stage.inputs) == ["data", "priors"]
    assert set(stage.config) == {"relation", "trainer", "seed"}


@pytest.mark.parametrize("backbone,size", [("conv_fc", 28), ("conv_fc_56", 56), ("conv_fc_56_ex4", 56),
                                           ("resnet18", 56)])
def test_every_backbone_composes_and_builds(backbone, size):
    rel = _compose(f"relation/backbone={backbone}").relation
    assert InputConfig.from_cfg(rel).input_size == size
    net = RelationNet(ModelConfig.from_cfg(rel)).eval()
    x = torch.zeros(1, 3, 7, size, size)
    adj = torch.eye(3).unsqueeze(0)
    with torch.no_grad():
        owner, _, _ = net(x, adj, torch.zeros(1, 3, 3))
    assert owner.shape == (1, 3, 3) and count_parameters(net) > 0 and size_mb(net) > 0


def test_training_seed_follows_the_root_seed_and_overrides_alone():
    assert _compose().relation.train.seed == 42
    assert _compose("seed=7").relation.train.seed == 7
    base, moved = _leaves(_compose()), _leaves(_compose("relation.train.seed=43"))
    assert {k for k in base if base[k] != moved[k]} == {"relation.train.seed"}  # the data keep seed 42
