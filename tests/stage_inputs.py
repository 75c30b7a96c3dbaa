"""A stage's ``inputs`` as the engine builds them (pipeline.outputs.StageInputs), for tests that call a stage's
``run`` directly: the declarations come from conf/config.yaml."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from pipeline.outputs import StageInputs

CONFIG = Path(__file__).resolve().parents[1] / "conf" / "config.yaml"


def stage_inputs(stage: str, dirs: dict[str, Path]) -> StageInputs:
    stages = OmegaConf.load(CONFIG).pipeline.stages
    declared = list(stages[stage].inputs)
    outputs = {name: OmegaConf.to_container(stages[name].get("outputs") or {}) for name in declared}
    return StageInputs(stage, dirs, declared, outputs)
