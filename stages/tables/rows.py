"""The rows of the paper's tables, each a configuration given by its Hydra overrides (the same ones the
``experiment`` sweeps run), and which runs are that row.

A run is a row when every parameter that defines the relation network and its training (``relation.*``
except the training budget -- epochs, patience, threads, image limits -- which the sweeps shorten, and the
training seed, whose spread is not another configuration) equals the row's composed configuration, composed
with the run's own profile (the profile resizes the network too). So a row can never drift from
``conf/table2_row`` or ``conf/ablation``: an ablated run is never the default row, whatever it ablates, nor
is a run trained on other data (``relation.train.detection_noise``, ``relation.box_warp``, ...).

The backbone is matched by its class, ``relation.backbone._target_``, and the arguments its config node holds. A run
logged before the node named its class has ``relation.backbone.name`` instead (and the arguments every backbone then
carried, used or not): its class is read from the name (``stages.relation.backbone_spec.backbone_target``), and the
fields the row's backbone does not take are not compared, as for any parameter the row does not define.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from pipeline.runs import RunRecord
from pipeline.tracker import flatten_params
from stages.relation.backbone_spec import TARGET, backbone_target

CONF = Path(__file__).resolve().parents[2] / "conf"
DEFINING_PREFIX = "relation."
# What the relation network trained on and from: a row is a network trained from scratch on the generator's data, so
# a run on other data (data=word, the adapt sweep's data=adapt) or started from other weights (init=run) is not one
# of its rows, whatever its relation settings.
DEFINING_KEYS = ("data.name", "init.source")
BACKBONE_TARGET = f"relation.backbone.{TARGET}"
NOT_DEFINING = frozenset(f"relation.train.{k}" for k in ("epochs", "patience", "threads", "seed",
                                                          "limit_train_images", "limit_val_images"))


@dataclass(frozen=True)
class Row:
    label: str
    overrides: tuple[str, ...]


TABLE1 = (Row("Conv+fc", ("experiment=table1", "relation/backbone=conv_fc")),
          Row("ResNet-18", ("experiment=table1", "relation/backbone=resnet18")))
TABLE2 = tuple(Row(label, ("experiment=table2", f"table2_row={name}")) for label, name in (
    ("Conv+fc", "conv_fc"), ("Neg0.1", "neg0.1"), ("-Neg", "fewer_neg"), ("-Sma", "small_mask"),
    ("56", "input56"), ("56_ex_4", "ex4")))
TABLE3_ROW = Row("DeepWORD (default)", ("experiment=table3",))


@functools.cache
def row_definition(row: Row, profile: str | None, conf_dir: Path = CONF) -> dict[str, str]:
    """The flattened parameters that define ``row`` under ``profile`` (None: the default profile), composed once
    per process (Hydra's compose API over ``conf_dir``: about half a second a row). Callers must not modify it."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    overrides = [*row.overrides, *([f"profile={profile}"] if profile else [])]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(conf_dir)):
            cfg = OmegaConf.to_container(compose("config", overrides=overrides), resolve=True)
    finally:
        GlobalHydra.instance().clear()
    return {k: v for k, v in flatten_params(cfg).items()
            if (k.startswith(DEFINING_PREFIX) and k not in NOT_DEFINING) or k in DEFINING_KEYS}


class RowMatcher:
    """Tells which runs are which row, from each row's composed configuration (``row_definition``)."""

    def __init__(self, conf_dir: Path = CONF):
        self.conf_dir = conf_dir

    def definition(self, row: Row, profile: str | None) -> dict[str, str]:
        """The flattened parameters that define ``row`` under ``profile`` (None: the default profile)."""
        return row_definition(row, profile, self.conf_dir)

    def matches(self, row: Row, run: RunRecord) -> bool:
        """Whether ``run`` is ``row``: its defining parameters equal the row's. A parameter the run does not
        have (a setting added after it ran) is not held against it."""
        profile = run.param("profile_name")
        params = run.params
        if BACKBONE_TARGET not in params and (target := backbone_target(params)) is not None:
            params = {**params, BACKBONE_TARGET: target}   # logged before the backbone node named its class
        return all(params.get(k, v) == v for k, v in self.definition(row, profile).items())
