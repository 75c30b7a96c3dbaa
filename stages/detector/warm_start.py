"""The detector's starting weights (the ``init`` group, stages/training/init_source.py; docs/stages.md, "init"): the stage's
plan-time ``resolve`` hook, its fine-tuning budget, and the loading of the weights before training."""

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

DETECTOR = Network("detector", "model.pt", "net.")
FREEZABLE = ("backbone", "heads")  # the detector's top-level parts (stages.detector.model.CenterNet)


def budget(train: dict, cfg) -> dict:
    """``init.detector_train`` with its nulls filled from the from-scratch budget (conf/init/_finetune.yaml)."""
    from omegaconf import OmegaConf

    det = OmegaConf.to_container(cfg.detector, resolve=True)

    def given(key, default):
        return default if train.get(key) is None else train[key]

    freeze = list(train.get("freeze") or [])
    unknown = [part for part in freeze if part not in FREEZABLE]
    if unknown:
        raise InitError(f"init.detector_train.freeze: unknown part(s) {unknown}; the detector's parts are {FREEZABLE}")
    return {"epochs": int(given("epochs", scaled_epochs(det["epochs"], cfg))),
            "lr": float(given("lr", float(det["optimizer"]["lr"]) / 3)),
            "warmup_fraction": float(given("warmup_fraction", det["optimizer"]["warmup_fraction"])),
            "ema_decay": float(given("ema_decay", det.get("ema_decay", 0.0))),
            "freeze": freeze}


def _group_of(path: Path):
    trained = Path(path).parent / "model.json"  # beside a detector stage's model.pt: what it was built with
    name = None
    if trained.is_file():
        try:
            backbone = json.loads(trained.read_text())["backbone"]
            # a model.json from before _target_ names the group option; a newer one the backbone's class
            name = (f"detector/backbone={backbone['name']}" if "name" in backbone else
                    f"detector/backbone (it was trained with {backbone['_target_']})")
        except (ValueError, KeyError, TypeError, AttributeError):
            name = None
    hint = name or "detector/backbone"

    def group_of(key: str) -> str:
        if key.startswith("backbone."):
            return hint
        return f"detector.regression and {hint} (its head_conv)"

    return group_of


def check(path: Path, state: dict, cfg) -> None:
    """Raise unless ``state`` loads into the detector the config builds (key by key, shape by shape)."""
    from omegaconf import OmegaConf

    # imported here: it loads torch, which importing this module must not
    from stages.detector.model import build_centernet, model_config

    expected = build_centernet(model_config(OmegaConf.to_container(cfg.detector, resolve=True))).state_dict()
    check_fits(without_new_facing(expected, state), state, path, "init.detector", _group_of(path))


FACING_PREFIX = "heads.facing."


def without_new_facing(expected: dict, state: dict) -> dict:
    """``expected`` without the facing head's keys when ``state`` has none (a run trained before the facing head, or
    with ``detector.facing=false``): that head alone starts from scratch; every other key must still fit."""
    if any(k.startswith(FACING_PREFIX) for k in state):
        return expected
    return {k: v for k, v in expected.items() if not k.startswith(FACING_PREFIX)}


def resolve(cfg, context) -> dict | None:
    """The detector stage's ``resolve`` hook (conf/config.yaml; pipeline.keys)."""
    return resolve_start(cfg, context, DETECTOR, budget, check)


def fine_tuning(det: dict, train: dict) -> dict:
    """The stage's ``detector`` settings with the fine-tuning budget (``init.train``) in place of the
    from-scratch one."""
    return {**det, "epochs": int(train["epochs"]), "ema_decay": float(train["ema_decay"]),
            "optimizer": {**det["optimizer"], "lr": float(train["lr"]),
                          "warmup_fraction": float(train["warmup_fraction"])}}


def load_start(net, path: Path) -> None:
    """The starting weights into ``net`` (all of them, but a facing head the start lacks: the hook checked every key
    and shape at plan time, ``without_new_facing``)."""
    state = load_state(Path(path), DETECTOR)
    missing, unexpected = net.load_state_dict(state, strict=False)
    if unexpected or any(not k.startswith(FACING_PREFIX) for k in missing):
        net.load_state_dict(state)  # strict: raises naming the keys
