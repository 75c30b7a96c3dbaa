"""Stage graph validation happens before any stage runs and names the stage and field."""

import pytest

from pipeline.dag import load_stages, select_stages
from pipeline.errors import PipelineError
from pipeline.runner import run_pipeline


def _fails_before_running(toy, cfg, match):
    with pytest.raises(PipelineError, match=match):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert not (toy.root / "cache").exists(), "nothing may be computed or created"


def test_unknown_input_is_reported_before_any_stage_runs(toy):
    cfg = toy.config(**{"pipeline.stages.b.inputs": ["a", "nope"]})
    _fails_before_running(toy, cfg, r"pipeline.stages.b.inputs: unknown stage\(s\) \['nope'\]")


def test_cycle_is_reported_with_its_path(toy):
    cfg = toy.config(**{"pipeline.stages.a.inputs": ["b"]})
    _fails_before_running(toy, cfg, r"dependency cycle a -> b -> a")


def test_unknown_config_key_is_reported(toy):
    cfg = toy.config(**{"pipeline.stages.c.config": ["gamma", "gama"]})
    _fails_before_running(toy, cfg, r"pipeline.stages.c.config: unknown top-level config key\(s\) \['gama'\]")


def test_malformed_run_and_unknown_field_are_reported(toy):
    _fails_before_running(toy, toy.config(**{"pipeline.stages.c.run": "no_colon"}), r"stages.c.run")
    _fails_before_running(toy, toy.config(**{"pipeline.stages.c.inptus": []}), r"unknown field")


def test_unknown_stage_in_force_or_until_errors_clearly(toy):
    _fails_before_running(toy, toy.config(**{"pipeline.force": ["zeta"]}), r"pipeline.force: unknown stage\(s\) \['zeta'\]")
    _fails_before_running(toy, toy.config(**{"pipeline.until": "zeta"}), r"pipeline.until: unknown stage")


def test_order_is_topological_and_until_selects_ancestors(toy):
    cfg = toy.config(**{"pipeline.stages.c.inputs": ["b"]})
    specs = load_stages(cfg)
    assert list(specs) == ["a", "b", "c"]
    assert select_stages(specs, "b") == (["a", "b"], {"c": "not needed for pipeline.until"})
    assert select_stages(specs, None) == (["a", "b", "c"], {})


def test_skip_leaves_out_the_stage_and_what_requires_it_but_not_what_can_do_without_it(toy):
    cfg = toy.config(**{"pipeline.stages.c.inputs": ["a"], "pipeline.stages.c.optional": ["a"]})
    specs = load_stages(cfg)
    assert select_stages(specs, None, ["a"]) == (["c"], {"a": "pipeline.skip", "b": "needs a"})
    assert select_stages(specs, "c", ["b"]) == (["a", "c"], {"b": "pipeline.skip"})
    with pytest.raises(PipelineError, match=r"pipeline.until=b: it needs a, which pipeline.skip leaves out"):
        select_stages(specs, "b", ["a"])


def test_bad_skip_and_optional_are_reported_before_any_stage_runs(toy):
    _fails_before_running(toy, toy.config(**{"pipeline.skip": ["zeta"]}), r"pipeline.skip: unknown stage\(s\) \['zeta'\]")
    _fails_before_running(toy, toy.config(**{"pipeline.skip": ["b"], "pipeline.until": "b"}),
                          r"pipeline.until=b is also in pipeline.skip")
    _fails_before_running(toy, toy.config(**{"pipeline.stages.c.optional": ["a"]}),
                          r"pipeline.stages.c.optional: \['a'\] not among its inputs \[\]")
