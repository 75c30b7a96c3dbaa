"""The ``estimate`` hook: called at plan time for the stages that will run (never for a hit), printed with the
total, a warning over ``pipeline.time_budget_minutes``, and the forecasts logged as the parent run's params."""

import sqlite3

import pytest

from pipeline.errors import PipelineError
from pipeline.estimate import Estimate, format_estimates
from pipeline.runner import run_pipeline

HOOKS = """
def _called(cfg, stage):
    with open(cfg.est.log, "a") as f:
        f.write(stage + "\\n")


def a(cfg, context):
    _called(cfg, "a")
    return {"seconds": cfg.est.a_seconds, "note": "toy probe", "hint": "lower est.a_seconds"}


def b(cfg, context):
    _called(cfg, "b")
    return cfg.est.b_seconds


def broken(cfg, context):
    _called(cfg, "c")
    raise RuntimeError("probe failed")
"""


def _config(toy, **dotted):
    toy.file("hooks.py").write_text(HOOKS)
    cfg = toy.config(**{"est.log": str(toy.root / "calls.txt"), "est.a_seconds": 600.0, "est.b_seconds": 300.0,
                        **dotted})
    cfg.pipeline.stages.a.estimate = f"{toy.package}.hooks:a"
    cfg.pipeline.stages.b.estimate = f"{toy.package}.hooks:b"
    cfg.pipeline.stages.c.estimate = f"{toy.package}.hooks:broken"
    return cfg


def _calls(toy):
    path = toy.root / "calls.txt"
    return sorted(path.read_text().split()) if path.exists() else []


def _params(toy, run_id):
    with sqlite3.connect(toy.root / "mlflow.db") as db:
        return dict(db.execute("select key, value from params where run_uuid = ? and key like 'estimate.%'",
                               (run_id,)).fetchall())


def test_estimates_only_missing_stages_prints_them_warns_and_logs(toy, capsys):
    summary = run_pipeline(_config(toy, **{"pipeline.time_budget_minutes": 10, "pipeline.until": "a"}),
                           run_dir=toy.root / "run", in_process_tracking=True)
    out = capsys.readouterr().out
    assert _calls(toy) == ["a"], "only the stages of this run"
    assert "Estimated time of the stages to run" in out and "toy probe" in out
    assert "WARNING" not in out, "600 s is within a 10-minute budget"
    assert summary["estimates"] == {"a": 600.0}
    assert _params(toy, summary["mlflow_run_id"]) == {"estimate.a.seconds": "600.0"}

    (toy.root / "calls.txt").unlink()
    summary = run_pipeline(_config(toy, **{"pipeline.time_budget_minutes": 10}), run_dir=toy.root / "run",
                           in_process_tracking=True)
    out = capsys.readouterr().out
    assert _calls(toy) == ["b", "c"], "a is a hit: its hook is not called"
    assert summary["estimates"] == {"b": 300.0, "c": None}
    assert "no estimate (RuntimeError: probe failed)" in out, "a failing hook costs the estimate, not the run"
    assert summary["stages"]["c"]["metrics"] == {"gamma.ok": 1.0, "gamma.inputs": 0.0}
    assert "WARNING" not in out
    assert _params(toy, summary["mlflow_run_id"]) == {"estimate.b.seconds": "300.0"}

    (toy.root / "calls.txt").unlink()
    summary = run_pipeline(_config(toy, **{"pipeline.time_budget_minutes": 10}), run_dir=toy.root / "run",
                           in_process_tracking=True)
    assert all(s["hit"] for s in summary["stages"].values())
    assert _calls(toy) == [] and "Estimated time" not in capsys.readouterr().out


def test_over_budget_names_the_slowest_stage_and_its_hint(toy, capsys):
    run_pipeline(_config(toy, **{"pipeline.time_budget_minutes": 12}), run_dir=toy.root / "run",
                 in_process_tracking=True)
    out = capsys.readouterr().out
    assert "total" in out and "15.0 min" in out
    warning = next(line for line in out.splitlines() if line.startswith("WARNING"))
    assert "'a' (~10.0 min): lower est.a_seconds" in warning and "12.0 min budget of profile toy" in warning


def test_no_budget_no_warning_and_a_bad_budget_is_a_config_error(toy, capsys):
    run_pipeline(_config(toy, **{"est.a_seconds": 1e6}), run_dir=toy.root / "run", in_process_tracking=True)
    assert "WARNING" not in capsys.readouterr().out
    with pytest.raises(PipelineError, match="time_budget_minutes"):
        run_pipeline(_config(toy, **{"pipeline.time_budget_minutes": "soon"}), run_dir=toy.root / "run2",
                     in_process_tracking=True)


def test_a_hook_returning_nonsense_is_reported_as_no_estimate():
    from pipeline.estimate import _check

    with pytest.raises(PipelineError, match="seconds"):
        _check("x", {"seconds": -1})
    with pytest.raises(PipelineError, match="unknown field"):
        _check("x", {"seconds": 1, "eta": 2})
    assert _check("x", 5) == Estimate("x", 5.0)
    assert format_estimates([Estimate("x", None, "no estimate (E: e)")], 60.0).splitlines()[-1].strip().endswith(
        "no estimate (E: e)")


def test_estimate_false_calls_no_hook(toy, capsys):
    summary = run_pipeline(_config(toy, **{"pipeline.estimate": False, "pipeline.time_budget_minutes": 1}),
                           run_dir=toy.root / "run", in_process_tracking=True)
    assert _calls(toy) == [] and "Estimated time" not in capsys.readouterr().out
    assert not summary.get("estimates") and not any(s["hit"] for s in summary["stages"].values())
