"""Stages that declare their threads run side by side within pipeline.cores (pipeline/schedule.py,
pipeline/stage_call.py): the waves, two real stages that can only finish together, a failure beside a success,
and the plan's estimate of a wave."""

from __future__ import annotations

import os
import textwrap

import mlflow
import pytest

from pipeline.errors import PipelineError
from pipeline.estimate import Estimate, format_estimates
from pipeline.runner import run_pipeline
from pipeline.schedule import waves

# The default pipeline's shape: data and priors run alone, the two one-thread trainings together, the detector
# (two threads) alone, then the rest.
ORDER = ["data", "shift_data", "priors", "relation", "detector", "facing", "export", "evaluate", "bev"]
INPUTS = {"data": (), "shift_data": (), "priors": ("data",), "relation": ("data", "priors"), "detector": ("data",),
          "facing": ("data",), "export": ("data", "priors", "relation", "detector", "facing"),
          "evaluate": ("data", "priors", "export", "shift_data", "detector"), "bev": ("data", "evaluate", "export")}
THREADS = {n: None for n in ORDER} | {"relation": 1, "facing": 1, "detector": 2}


def test_the_default_pipelines_waves_on_two_cores():
    assert waves(ORDER, INPUTS, THREADS, 2) == [
        ["data"], ["shift_data"], ["priors"], ["relation", "facing"], ["detector"], ["export"], ["evaluate"], ["bev"]]


def test_more_cores_fit_more_stages_in_a_wave_and_on_one_every_stage_runs_alone():
    assert ["relation", "detector", "facing"] in waves(ORDER, INPUTS, THREADS, 4)
    assert all(len(w) == 1 for w in waves(ORDER, INPUTS, THREADS, 1))
    assert [n for w in waves(ORDER, INPUTS, THREADS, 1) for n in w] == ORDER


def test_stages_whose_ranks_follow_the_engine_never_share_a_wave():
    # every_rank stages (relation, detector) run in the engine's process, whose command other ranks re-run
    assert waves(ORDER, INPUTS, THREADS, 4, {"relation", "detector"})[3:5] == [["relation", "facing"], ["detector"]]


def test_a_wave_never_holds_a_stage_and_its_input_nor_one_that_declares_no_threads():
    threads = {"a": 1, "b": 1, "c": None, "d": 1}
    inputs = {"a": (), "b": ("a",), "c": (), "d": ()}
    assert waves(["a", "b", "c", "d"], inputs, threads, 8) == [["a", "d"], ["b"], ["c"]]
    # an input that is not computed (a cache hit) is ready from the start
    assert waves(["b", "d"], inputs, threads, 8) == [["b", "d"]]


MEET = """
import os
import time
from pathlib import Path


def run(cfg, inputs, out_dir):
    # Both stages of the test must be running at once: each says it is here and waits for the other.
    me = cfg[next(k for k in cfg if k.startswith("meet"))]
    Path(me.dir, me.name).write_text(str(os.getpid()))
    deadline = time.monotonic() + 60
    while not Path(me.dir, me.other).exists():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{me.name} never met {me.other}: the stages did not run side by side")
        time.sleep(0.05)
    (out_dir / "pid.txt").write_text(str(os.getpid()))
    if me.fail == "raise":
        raise ValueError(f"{me.name} failed on purpose")
    if me.fail == "die":
        os._exit(3)  # as if killed: no answer
    return {f"{me.name}.met": 1.0}
"""


def _meeting(toy, fail: str = "", how: str = "raise", every_rank: str = ""):
    (toy.root / toy.package / "meet").mkdir()
    (toy.root / toy.package / "meet" / "__init__.py").write_text("")
    (toy.root / toy.package / "meet" / "stage.py").write_text(textwrap.dedent(MEET))
    rendezvous = toy.root / "rendezvous"
    rendezvous.mkdir(exist_ok=True)
    dotted = {"pipeline__cores": 2}
    for me, other in (("m1", "m2"), ("m2", "m1")):
        dotted[f"meet_{me}"] = {"name": me, "other": other, "dir": str(rendezvous), "threads": 1,
                                "fail": how if me == fail else ""}
        dotted[f"pipeline__stages__{me}"] = {"run": f"{toy.package}.meet.stage:run", "inputs": ["a"],
                                             "config": [f"meet_{me}"], "threads": f"meet_{me}.threads",
                                             "every_rank": me == every_rank}
    return toy.config(**dotted), rendezvous


def test_two_stages_that_declare_one_thread_run_at_once_in_processes_of_their_own(toy, capsys):
    cfg, rendezvous = _meeting(toy)
    summary = run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    out = capsys.readouterr().out
    assert list(summary["stages"]) == ["a", "b", "c", "m1", "m2"]  # the plan's order in the summary
    pids = {int((toy.root / "rendezvous" / n).read_text()) for n in ("m1", "m2")}
    assert len(pids) == 2 and os.getpid() not in pids
    assert "Running stage 'm1' (no entry yet; beside 'm2')" in out
    assert "'m1' still running" in out or "'m2' still running" in out
    for name in ("m1", "m2"):
        stage = summary["stages"][name]
        assert not stage["hit"] and stage["metrics"] == {f"{name}.met": 1.0}
        run = mlflow.MlflowClient(toy.db_uri).get_run(stage["mlflow_run_id"])
        assert run.info.status == "FINISHED" and run.data.metrics[f"{name}.met"] == 1.0
    for path in rendezvous.iterdir():
        path.unlink()
    again = run_pipeline(cfg, run_dir=toy.root / "again", in_process_tracking=True)
    assert all(s["hit"] for s in again["stages"].values())


def test_an_every_rank_stage_runs_in_the_engines_process_beside_the_others(toy):
    cfg, rendezvous = _meeting(toy, every_rank="m1")
    summary = run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert int((rendezvous / "m1").read_text()) == os.getpid() != int((rendezvous / "m2").read_text())
    assert summary["stages"]["m1"]["metrics"] == {"m1.met": 1.0} and not summary["stages"]["m2"]["hit"]


def test_a_stage_that_fails_beside_another_keeps_the_others_entry_and_reports_its_own_error(toy):
    cfg, rendezvous = _meeting(toy, fail="m2")
    with pytest.raises(ValueError, match="m2 failed on purpose") as failure:
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert failure.value.pipeline_stage == "m2"
    assert 'raise ValueError(f"{me.name} failed on purpose")' in failure.value.stage_traceback
    client = mlflow.MlflowClient(toy.db_uri)
    m2_runs = client.search_runs([client.get_experiment_by_name("toy").experiment_id], "tags.stage = 'm2'")
    assert [r.info.status for r in m2_runs] == ["FAILED"]
    assert not [p for p in (toy.root / "cache" / "m2").iterdir() if p.name.startswith(".partial-")], \
        "a failure leaves no work dir to resume from"
    cfg.meet_m2.fail = ""  # alone now (m1 is a hit), it finds m1's word from before
    summary = run_pipeline(cfg, run_dir=toy.root / "fixed", in_process_tracking=True)
    assert summary["stages"]["m1"]["hit"], "what m1 computed beside the failure was kept"
    assert not summary["stages"]["m2"]["hit"]


def test_a_stage_whose_process_dies_keeps_its_work_dir_for_a_re_run(toy):
    cfg, _ = _meeting(toy, fail="m2", how="die")
    with pytest.raises(PipelineError, match="stage 'm2': its process exited with code 3 before it answered"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    partial = [p for p in (toy.root / "cache" / "m2").iterdir() if p.name.startswith(".partial-")]
    assert len(partial) == 1 and (partial[0] / "out" / "pid.txt").is_file(), "what it wrote is kept"
    cfg.meet_m2.fail = ""
    summary = run_pipeline(cfg, run_dir=toy.root / "again", in_process_tracking=True)
    assert summary["stages"]["m1"]["hit"] and not summary["stages"]["m2"]["hit"]


def test_a_threads_key_outside_the_stages_config_is_refused(toy):
    cfg = toy.config(pipeline__stages__c__threads="alpha.value")
    with pytest.raises(PipelineError, match=r"pipeline.stages.c.threads: expected a key under its config \['gamma'\]"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    cfg = toy.config(pipeline__stages__c__threads="gamma.x", gamma__x="two")
    with pytest.raises(PipelineError, match="config key 'gamma.x' should hold an integer >= 1"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)


def test_the_plans_total_counts_a_wave_as_its_longest_stage():
    estimates = [Estimate("relation", 400.0, "40 epochs"), Estimate("facing", 300.0, "20 epochs"),
                 Estimate("detector", 900.0)]
    text = format_estimates(estimates, None, "", [["relation", "facing"], ["detector"]])
    assert "relation    6.7 min  40 epochs; beside facing" in text
    assert "total      21.7 min" in text and "count as the longest of them" in text
    alone = format_estimates(estimates, None, "", [["relation"], ["facing"], ["detector"]])
    assert "total      26.7 min" in alone and "beside" not in alone
