"""The ``size`` hook: a budget sized to the host at plan time, set in the config as if given on the command line
(the key, the stage and the params see it), printed, logged as ``sized.<key>``, remembered per host and config."""

import hashlib
import sqlite3
import tempfile
from pathlib import Path

import pytest

from pipeline import sizing
from pipeline.errors import PipelineError
from pipeline.runner import run_pipeline

HOOKS = """
def size(cfg, context):
    with open(cfg.est.log, "a") as f:
        f.write("probe\\n")
    if cfg.alpha.value != "auto":
        return None
    return {"config": {"alpha.value": cfg.est.fits}, "note": "toy probe"}


def slow(cfg, context):
    import time
    with open(cfg.est.log, "a") as f:
        f.write("probe\\n")
    time.sleep(0.5)
    return {"config": {"alpha.value": cfg.est.fits}, "note": "slow toy probe"}


def outside(cfg, context):
    return {"config": {"beta.offset": 1}, "note": ""}


def broken(cfg, context):
    raise ValueError("no clock on this host")
"""


def _config(toy, hook="size", **dotted):
    toy.file("hooks.py").write_text(HOOKS)
    cfg = toy.config(**{"est.log": str(toy.root / "calls.txt"), "est.fits": 5, "pipeline.until": "a", **dotted})
    cfg.pipeline.stages.a.size = f"{toy.package}.hooks:{hook}"
    return cfg


def _probes(toy):
    path = toy.root / "calls.txt"
    return len(path.read_text().split()) if path.exists() else 0


def _params(toy, run_id):
    with sqlite3.connect(toy.root / "mlflow.db") as db:
        return dict(db.execute("select key, value from params where run_uuid = ? and key in ('sized.alpha.value', "
                               "'alpha.value')", (run_id,)).fetchall())


def test_auto_is_sized_printed_logged_and_keyed_as_the_explicit_value(toy, capsys):
    summary = run_pipeline(_config(toy, **{"alpha.value": "auto"}), run_dir=toy.root / "run",
                           in_process_tracking=True)
    out = capsys.readouterr().out
    assert _probes(toy) == 1
    assert summary["stages"]["a"]["metrics"]["alpha.value"] == 10.0, "the stage read the sized value (2 x 5)"
    assert summary["sized"] == {"alpha.value": 5}
    assert "Sized to this host" in out and "a: alpha.value=5: toy probe" in out
    assert _params(toy, summary["mlflow_run_id"]) == {"sized.alpha.value": "5", "alpha.value": "5"}
    sized_key = summary["stages"]["a"]["key"]

    # the same value given explicitly: the same cache entry, and the same run (already recorded)
    explicit = run_pipeline(_config(toy, **{"alpha.value": 5}), run_dir=toy.root / "run2", in_process_tracking=True)
    assert explicit["stages"]["a"]["key"] == sized_key and explicit["stages"]["a"]["hit"]
    assert explicit["mlflow_run_id"] == summary["mlflow_run_id"]
    assert "Sized to this host" not in capsys.readouterr().out, "an explicit value is not sized (the hook said None)"


def test_a_sizing_is_remembered_per_host_and_config(toy, capsys, monkeypatch):
    run_pipeline(_config(toy, **{"alpha.value": "auto"}), run_dir=toy.root / "run", in_process_tracking=True)
    # the probe would now answer 7, but the remembered 5 holds: the stage is a hit, not trained again
    again = run_pipeline(_config(toy, **{"alpha.value": "auto", "est.fits": 7}), run_dir=toy.root / "run2",
                         in_process_tracking=True)
    assert _probes(toy) == 1 and again["sized"] == {"alpha.value": 5} and again["stages"]["a"]["hit"]
    assert "remembered in" in capsys.readouterr().out
    monkeypatch.setattr(sizing, "host_fingerprint", lambda: "another host")
    elsewhere = run_pipeline(_config(toy, **{"alpha.value": "auto", "est.fits": 7}), run_dir=toy.root / "run3",
                             in_process_tracking=True)
    assert _probes(toy) == 2 and elsewhere["sized"] == {"alpha.value": 7} and not elsewhere["stages"]["a"]["hit"]


def test_a_hook_that_fails_or_sizes_another_stages_config_stops_the_plan(toy):
    with pytest.raises(PipelineError, match="stage 'a': cannot size it to this host: no clock on this host"):
        run_pipeline(_config(toy, hook="broken"), run_dir=toy.root / "run", in_process_tracking=True)
    with pytest.raises(PipelineError, match=r"sized \['beta.offset'\], outside the stage's config"):
        run_pipeline(_config(toy, hook="outside"), run_dir=toy.root / "run", in_process_tracking=True)
    assert not (toy.root / "cache" / "a").exists(), "nothing ran"


def test_a_bad_value_stops_the_run_before_the_probe_and_the_sized_value_is_checked_once_sized(toy):
    checks = {"alpha.value": ">= 1", "beta.offset": ">= 0"}
    cfg = _config(toy, **{"alpha.value": "auto", "beta.offset": -1})
    cfg.pipeline.stages.a.checks = checks
    with pytest.raises(PipelineError, match=r"beta.offset = -1: must be >= 0"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert _probes(toy) == 0, "a bad value elsewhere stops the run before the probe"
    assert not (toy.root / "cache" / ".sizing.json").exists(), "and nothing is remembered"

    cfg = _config(toy, **{"alpha.value": "auto", "est.fits": 0})   # the hook sizes to 0: checked once sized
    cfg.pipeline.stages.a.checks = checks
    with pytest.raises(PipelineError, match=r"alpha.value = 0: must be >= 1"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert _probes(toy) == 1 and not (toy.root / "cache" / "a").exists()


def _size_in_a_process(cfg, cache):
    from pipeline.dag import load_stages

    specs = load_stages(cfg)
    return sizing.size_stages(specs, ["a"], cfg, cache, None)[0].alpha.value


def test_processes_sizing_side_by_side_probe_once_and_agree(toy):
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    cfg = _config(toy, hook="slow", **{"alpha.value": "auto"})
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as pool:
        values = list(pool.map(_size_in_a_process, [cfg, cfg], [toy.root / "cache"] * 2))
    assert values == [5, 5] and _probes(toy) == 1, "the second waited for the first and read its answer"
    digest = hashlib.sha256(str((toy.root / "cache").absolute()).encode()).hexdigest()[:16]
    assert not (Path(tempfile.gettempdir()) / f"pipeline-sizing-{digest}.lock").exists(), "no lock file left behind"
