"""Multi-process launches (pipeline.ranks): which rank a process is, and (slow, real processes on the toy
project) two ranks of one launch: rank 0 alone computes, tracks and writes; rank 1 joins the stage declared
``every_rank`` with the same committed inputs and writes nothing; a failure or a different plan on rank 0
stops rank 1 with a message instead of a hang."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

import mlflow
import pytest
from omegaconf import OmegaConf

from pipeline.errors import PipelineError
from pipeline.ranks import LAUNCH_ID_VARIABLE, current_rank

REPO = Path(__file__).resolve().parents[2]

RUNNER = """
import sys
from pathlib import Path
from omegaconf import OmegaConf
from pipeline.runner import run_pipeline
cfg = OmegaConf.load(sys.argv[1])
run_pipeline(cfg, run_dir=Path(sys.argv[2]), in_process_tracking=True)
"""

# Stage b of the toy project, recording every call (which rank, the input it got, where it wrote) and, like
# a DDP fit, returning only when both ranks of the launch have called it.
RECORDING_BETA = """
import os
import time


def run(cfg, inputs, out_dir):
    value = int((inputs["a"] / "value.txt").read_text())
    (out_dir / "sum.txt").write_text(str(value + cfg.beta.offset))
    calls, launch = os.environ["BETA_CALLS"], os.environ["PIPELINE_LAUNCH_ID"]
    with open(calls, "a") as f:
        f.write(f"{os.environ['RANK']} {inputs['a']} {out_dir} {launch}\\n")
    deadline = time.monotonic() + float(os.environ.get("BETA_BARRIER_S", "60"))
    while sum(launch in line for line in open(calls)) < 2:
        if time.monotonic() > deadline:
            raise RuntimeError("the other rank never joined stage b")
        time.sleep(0.05)
    return {"beta.sum": float(value + cfg.beta.offset)}
"""


@pytest.mark.parametrize(("environ", "expected"), [
    ({}, (0, 1, None)),
    ({"RANK": "1", "WORLD_SIZE": "4", "LOCAL_RANK": "1", "TORCHELASTIC_RUN_ID": "abc"}, (1, 4, "torchrun-abc")),
    ({"SLURM_PROCID": "2", "SLURM_NTASKS": "8", "SLURM_JOB_ID": "77", "SLURM_STEP_ID": "0"}, (2, 8, "slurm-77.0.0")),
    ({"SLURM_PROCID": "0", "SLURM_NTASKS": "1", "SLURM_JOB_ID": "77"}, (0, 1, None)),  # a sweep job: alone
    ({"LOCAL_RANK": "1", "NODE_RANK": "0", "WORLD_SIZE": "2", LAUNCH_ID_VARIABLE: "local-9"}, (1, 2, "local-9")),
    ({"LOCAL_RANK": "0", "NODE_RANK": "0", "WORLD_SIZE": "2", LAUNCH_ID_VARIABLE: "local-9"}, (0, 2, "local-9")),
])
def test_rank_world_size_and_launch_id_come_from_the_launchers_variables(environ, expected):
    rank = current_rank(environ)
    assert (rank.index, rank.world_size, rank.launch_id) == expected
    assert rank.is_zero == (expected[0] == 0)


def test_a_malformed_rank_variable_is_named():
    with pytest.raises(PipelineError, match="RANK='one'"):
        current_rank({"RANK": "one", "WORLD_SIZE": "2"})


def _start_rank(toy, cfg, rank: int, launch_id: str, name: str, barrier_s: float) -> subprocess.Popen:
    cfg_path = toy.root / f"{name}.yaml"
    OmegaConf.save(cfg, cfg_path)
    env = {**os.environ, "PYTHONPATH": f"{toy.root}{os.pathsep}{REPO}", "RANK": str(rank), "WORLD_SIZE": "2",
           LAUNCH_ID_VARIABLE: launch_id, "BETA_CALLS": str(toy.root / "beta_calls.txt"), "BETA_BARRIER_S": str(barrier_s)}
    return subprocess.Popen([sys.executable, "-c", RUNNER, str(cfg_path), str(toy.root / name)], cwd=toy.root,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _launch(toy, cfg, name: str, cfg_rank1=None, barrier_s: float = 60) -> tuple[subprocess.Popen, str, subprocess.Popen, str]:
    launch_id = f"test-{uuid.uuid4().hex[:8]}"
    procs = [_start_rank(toy, cfg if r == 0 else (cfg_rank1 or cfg), r, launch_id, f"{name}_rank{r}", barrier_s)
             for r in (0, 1)]
    (out0, _), (out1, _) = (p.communicate(timeout=120) for p in procs)
    return procs[0], out0, procs[1], out1


def _every_rank_toy(toy, **dotted):
    toy.edit("beta/stage.py", RECORDING_BETA)
    # alpha sleeps: rank 1 reaches b long before rank 0 has committed a, and must wait for it
    return toy.config(**{"pipeline.stages.b.every_rank": True, "alpha.sleep": 1, "alpha.counter": str(toy.root / "a.txt"),
                         **dotted})


@pytest.mark.slow
def test_rank_one_joins_the_every_rank_stage_on_committed_inputs_and_writes_nothing(toy):
    cfg = _every_rank_toy(toy)
    rank0, out0, rank1, out1 = _launch(toy, cfg, "first")
    assert rank0.returncode == 0 and rank1.returncode == 0, out0 + out1
    assert "rank 1 of 2" in out1 and "joining stage 'b'" in out1 and "done (joined ['b'])" in out1

    calls = [line.split() for line in (toy.root / "beta_calls.txt").read_text().splitlines()]
    assert sorted(c[0] for c in calls) == ["0", "1"]
    (a_entry,) = [p for p in (toy.root / "cache" / "a").iterdir() if not p.name.startswith(".") and p.is_dir()]
    assert {c[1] for c in calls} == {str(a_entry / "out")}, "both ranks read the committed entry of a"
    rank1_out = Path(next(c[2] for c in calls if c[0] == "1"))
    assert not rank1_out.exists() and not str(rank1_out).startswith(str(toy.root / "cache"))

    for stage in ("a", "b", "c"):  # one entry per stage, nothing half-written, no launch file left behind
        names = [p.name for p in (toy.root / "cache" / stage).iterdir()]
        assert len([n for n in names if not n.startswith(".") and n != "latest.json"]) == 1, names
        assert not [n for n in names if n.startswith((".partial-", ".trash-"))], names
    assert not list((toy.root / "cache" / ".launches").glob("*.json"))
    assert (toy.root / "first_rank0" / "summary.json").is_file()
    assert not (toy.root / "first_rank1").exists(), "rank 1 writes no summary"
    assert (toy.root / "a.txt").read_text().count("computed") == 1

    mlflow.set_tracking_uri(toy.db_uri)
    runs = mlflow.search_runs(experiment_names=["toy"], output_format="list")
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(parents) == 1 and sorted(r.info.run_name for r in runs if r not in parents) == ["a", "b", "c"]

    # A second launch finds every entry: rank 1 has nothing to join and stage b runs nowhere.
    rank0, out0, rank1, out1 = _launch(toy, cfg, "second")
    assert rank0.returncode == 0 and rank1.returncode == 0, out0 + out1
    assert "stage 'b' is in the cache, nothing to join" in out1
    assert len((toy.root / "beta_calls.txt").read_text().splitlines()) == 2

    # Forced, b is computed again although its entry exists: rank 1 must join it, not skip it.
    rank0, out0, rank1, out1 = _launch(toy, OmegaConf.merge(cfg, {"pipeline": {"force": ["b"]}}), "forced")
    assert rank0.returncode == 0 and rank1.returncode == 0, out0 + out1
    assert "joining stage 'b'" in out1
    assert sorted(line.split()[0] for line in (toy.root / "beta_calls.txt").read_text().splitlines()) == ["0", "0", "1", "1"]


@pytest.mark.slow
def test_a_failing_rank_zero_stops_the_other_rank_with_its_error(toy):
    rank0, out0, rank1, out1 = _launch(toy, _every_rank_toy(toy, **{"alpha.fail": True}), "failing")
    assert rank0.returncode != 0 and "alpha failed on purpose" in out0
    assert rank1.returncode != 0 and "rank 0 of launch test-" in out1 and "alpha failed on purpose" in out1
    assert not (toy.root / "beta_calls.txt").exists()
    launch_files = list((toy.root / "cache" / ".launches").glob("*.json"))
    assert len(launch_files) == 1 and "alpha failed" in json.loads(launch_files[0].read_text())["error"]


@pytest.mark.slow
def test_ranks_with_different_configs_refuse_to_train_together(toy):
    cfg = _every_rank_toy(toy)
    other = OmegaConf.merge(cfg, {"beta": {"offset": 11}})
    # rank 1 leaves, so rank 0's stage b waits for it in vain (a DDP fit would until its timeout): briefly here
    rank0, out0, rank1, out1 = _launch(toy, cfg, "mismatch", cfg_rank1=other, barrier_s=1)
    assert rank1.returncode != 0 and "rank 0 planned other cache keys for stage(s) ['b']" in out1
    assert "different code or config" in out1
