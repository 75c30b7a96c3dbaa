"""The relation network's starting weights (the ``init`` group, stages/training/init_source.py; docs/stages.md, "init"):
the stage's plan-time ``resolve`` hook, its fine-tuning budget, and the weights each ensemble member starts from.

A relation stage ships one network or an ensemble (``relation.ensemble``). Weights of as many members start
each member from its own; the weights of one network start every member (they then differ by their seeds'
shuffling, augmentation and simulated detections only). Other counts are an error naming relation.ensemble."""

from __future__ import annotations

import json
from pathlib import Path

from stages.training.init_source import (
    InitError,
    Network,
    check_fits,
    load_state,
    resolve_start,
    scaled_epochs,
)

RELATION = Network("relation", "relation.pt", "model.")
MEMBERS = "members."


def budget(train: dict, cfg) -> dict:
    """``init.relation_train`` with its nulls filled from the from-scratch budget (conf/init/_finetune.yaml)."""
    tr = cfg.relation.train

    def given(key, default):
        return default if train.get(key) is None else train[key]

    return {"epochs": int(given("epochs", scaled_epochs(tr.epochs, cfg))),
            "lr": float(given("lr", float(tr.lr) / 3)),
            "patience": int(given("patience", tr.patience)),
            "ema_decay": float(given("ema_decay", tr.get("ema_decay", 0.0))),
            "select": str(given("select", tr.get("select", "wheel_acc")))}


def members_of(state: dict) -> list[dict]:
    """A RelationEnsemble's state_dict as its members' (in order); a RelationNet's as one."""
    if not any(k.startswith(MEMBERS) for k in state):
        return [state]
    members: dict[int, dict] = {}
    for key, value in state.items():
        index, _, rest = key.removeprefix(MEMBERS).partition(".")
        members.setdefault(int(index), {})[rest] = value
    return [members[i] for i in sorted(members)]


def member_states(state: dict, n_members: int, path: Path) -> list[dict]:
    """The starting state_dict of each of ``n_members`` networks."""
    members = members_of(state)
    if len(members) == n_members:
        return members
    if len(members) == 1:
        return members * n_members
    raise InitError(f"init.relation: {path} holds an ensemble of {len(members)} networks, the config asks for "
                    f"{n_members}: set relation.ensemble={len(members)} (or start from one network's weights)")


def _group_of(path: Path):
    trained = Path(path).parent / "relation.json"
    hint = "relation/backbone"
    if trained.is_file():  # beside a relation stage's relation.pt: what it was built with
        # imported here: it loads torch, which importing this module must not
        from stages.relation.model import ModelConfig

        try:
            backbone = ModelConfig.of(json.loads(trained.read_text())["model"]).backbone
            hint += " (it was trained with backbone " + ", ".join(f"{k} {v}" for k, v in backbone.items()) + ")"
        except (ValueError, KeyError, TypeError):
            pass

    def group_of(key: str) -> str:
        if key.startswith("backbone."):
            return hint
        return "relation.model (or the ablation group) and " + hint

    return group_of


def check(path: Path, state: dict, cfg) -> None:
    """Raise unless every member's weights load into the relation network the config builds."""
    # imported here: it loads torch, which importing this module must not
    from stages.relation.model import ModelConfig, RelationNet

    expected = RelationNet(ModelConfig.from_cfg(cfg.relation)).state_dict()
    for member in member_states(state, int(cfg.relation.get("ensemble", 1)), path):
        check_fits(expected, member, path, "init.relation", _group_of(path))


def resolve(cfg, context) -> dict | None:
    """The relation stage's ``resolve`` hook (conf/config.yaml; pipeline.keys)."""
    return resolve_start(cfg, context, RELATION, budget, check)


def fine_tuning(cfg, train: dict):
    """The stage config with the fine-tuning budget (``init.train``) in place of relation.train's from-scratch one."""
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg, resolve=True)
    plain["relation"]["train"].update(epochs=int(train["epochs"]), lr=float(train["lr"]),
                                      patience=int(train["patience"]), ema_decay=float(train["ema_decay"]),
                                      select=str(train["select"]))
    return OmegaConf.create(plain)


def start_states(path: Path, n_members: int) -> list[dict]:
    """Each member's starting state_dict (checked at plan time)."""
    return member_states(load_state(Path(path), RELATION), n_members, Path(path))
