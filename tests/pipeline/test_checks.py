"""Declared value checks (pipeline/checks.py): a value breaking a rule stops the run before any stage."""

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from pipeline.checks import check_values, parse_checks
from pipeline.errors import PipelineError
from pipeline.runner import run_pipeline


def checks(mapping):
    return parse_checks("a", OmegaConf.create(mapping))


@pytest.mark.parametrize("value, rules", [(1, ">= 1"), (0.5, ["> 0", "<= 1"]), (None, [None, ">= 1"]),
                                          (1e-9, "> 0"), (-3, "< -2.5")])
def test_values_inside_their_rules_pass(value, rules):
    check_values(OmegaConf.create({"x": {"y": value}}), "a", checks({"x.y": rules}))


@pytest.mark.parametrize("value, rules, words", [
    (-1, ">= 1", "x.y = -1: must be >= 1"),
    (1.5, ["> 0", "<= 1"], "x.y = 1.5: must be <= 1"),
    (None, ">= 1", "x.y = null: must be a number"),
    ("ten", ">= 1", "x.y = 'ten': must be a number"),
    (True, ">= 0", "must be a number"),
    (float("nan"), ">= 0", "must be a number"),
])
def test_value_breaking_a_rule_names_key_value_and_rule(value, rules, words):
    with pytest.raises(PipelineError, match="declared in pipeline.stages.a.checks") as info:
        check_values(OmegaConf.create({"x": {"y": value}}), "a", checks({"x.y": rules}))
    assert words in str(info.value)


def test_check_on_a_missing_key_is_an_error():
    with pytest.raises(PipelineError, match="x.z: not in the config"):
        check_values(OmegaConf.create({"x": {"y": 1}}), "a", checks({"x.z": ">= 1"}))


@pytest.mark.parametrize("rule", ["=> 1", "== 1", ">= one", 3, ">="])
def test_malformed_rule_is_rejected_naming_stage_and_key(rule):
    with pytest.raises(PipelineError, match=r"pipeline.stages.a.checks.x.y: rule"):
        checks({"x.y": rule})


def test_failed_check_runs_no_stage_and_checks_only_stages_that_would_run(toy):
    cfg = toy.config(**{"pipeline.stages.b.checks": {"beta.offset": "< 5"}})
    with pytest.raises(PipelineError, match="beta.offset = 10: must be < 5"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert not Path(toy.root / "cache").exists()
    cfg = toy.config(**{"pipeline.stages.b.checks": {"beta.offset": "< 5"}, "pipeline.until": "a"})
    summary = run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert list(summary["stages"]) == ["a"]
