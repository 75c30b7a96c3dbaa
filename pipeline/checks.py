"""Declared value checks (``pipeline.stages.<name>.checks``), run before any stage.

A stage declares rules for config values it reads, e.g. ``checks: {relation.train.epochs: ">= 1"}`` or
several rules for one key, ``[">= 0", "<= 1"]``; ``null`` among them allows a null value. The engine
checks every rule of every stage about to run before planning, so ``relation.train.epochs=-1`` fails in a
second instead of after the upstream stages ran. Checks are not part of any cache key: they decide only
whether a run may start.
"""

from __future__ import annotations

import math
import operator
import re

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.errors import PipelineError

OPS = {">=": operator.ge, ">": operator.gt, "<=": operator.le, "<": operator.lt}
_RULE = re.compile(r"^\s*(>=|<=|>|<)\s*([-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)\s*$")
NULL = "null"
_ABSENT = object()


def parse_checks(stage: str, node) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """Validate the ``checks`` field of a stage declaration: {config key: rule or [rules]}."""
    where = f"pipeline.stages.{stage}.checks"
    if node is None:
        return ()
    if not isinstance(node, DictConfig):
        raise PipelineError(f"{where}: expected a mapping of config keys to rules, got {node!r}")
    out = []
    for key in node:
        raw = node[key]
        rules = tuple(OmegaConf.to_container(raw)) if isinstance(raw, ListConfig) else (raw,)
        rules = tuple(NULL if r is None else r for r in rules)  # YAML's bare null
        for rule in rules:
            if not isinstance(rule, str) or (rule != NULL and not _RULE.match(rule)):
                raise PipelineError(f"{where}.{key}: rule {rule!r} is not one of '>= N', '> N', '<= N', "
                                    f"'< N' or 'null'")
        out.append((str(key), rules))
    return tuple(out)


def _fails(value, rule: str) -> bool:
    op, bound = _RULE.match(rule).group(1, 2)
    return not OPS[op](value, float(bound))


def check_values(cfg: DictConfig, stage: str, checks: tuple[tuple[str, tuple[str, ...]], ...]) -> None:
    """Raise a PipelineError naming the key, its value and the rule for the first value that breaks one."""
    for key, rules in checks:
        value = OmegaConf.select(cfg, key, default=_ABSENT)
        declared = f"(declared in pipeline.stages.{stage}.checks); no stage was run"
        if value is _ABSENT:
            raise PipelineError(f"{key}: not in the config, but stage '{stage}' checks it {declared}")
        if value is None:
            if NULL not in rules:
                raise PipelineError(f"{key} = null: must be a number {declared}")
            continue
        if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
            raise PipelineError(f"{key} = {value!r}: must be a number {declared}")
        broken = [r for r in rules if r != NULL and _fails(value, r)]
        if broken:
            raise PipelineError(f"{key} = {value}: must be {' and '.join(broken)} {declared}")
