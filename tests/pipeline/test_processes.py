"""Real processes: SIGKILL mid-stage, two pipelines racing for one key, and the Hydra CLI end to end."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[2]

RUNNER = """
import sys
from pathlib import Path
from omegaconf import OmegaConf
from pipeline.runner import run_pipeline
cfg = OmegaConf.load(sys.argv[1])
run_pipeline(cfg, run_dir=Path(sys.argv[2]), in_process_tracking=True)
"""


def _env(toy):
    return {**os.environ, "PYTHONPATH": f"{toy.root}{os.pathsep}{REPO}"}


def _start(toy, cfg, name):
    cfg_path = toy.root / f"{name}.yaml"
    OmegaConf.save(cfg, cfg_path)
    return subprocess.Popen(
        [sys.executable, "-c", RUNNER, str(cfg_path), str(toy.root / name)],
        cwd=toy.root, env=_env(toy), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )


def _wait_for(path: Path, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.05)


@pytest.mark.slow
def test_sigkill_mid_stage_leaves_no_complete_entry_and_rerun_computes(toy):
    counter = toy.root / "count.txt"
    cfg = toy.config(**{"alpha.counter": str(counter), "alpha.sleep": 60})
    proc = _start(toy, cfg, "killed")
    _wait_for(Path(f"{counter}.started"))
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    stage_dir = toy.root / "cache" / "a"
    assert [p.name for p in stage_dir.iterdir() if not p.name.startswith(".")] == [], "no complete-looking entry"
    assert any(p.name.startswith(".partial-") for p in stage_dir.iterdir()), "the kill left its work dir"

    Path(f"{counter}.nosleep").write_text("")  # same config (same key), no sleep this time
    rerun = _start(toy, cfg, "rerun")
    out, _ = rerun.communicate(timeout=120)
    assert rerun.returncode == 0, out
    assert "Running stage 'a'" in out and "resuming from what an interrupted attempt left" in out
    assert not any(p.name.startswith(".partial-") for p in stage_dir.iterdir()), "work dir became the entry"
    summary = json.loads((toy.root / "rerun" / "summary.json").read_text())
    assert summary["stages"]["a"]["hit"] is False and counter.read_text().count("computed") == 2


@pytest.mark.slow
def test_two_concurrent_pipelines_compute_a_shared_stage_once(toy):
    counter = toy.root / "count.txt"
    cfg = toy.config(**{"alpha.counter": str(counter), "alpha.sleep": 3})
    procs = [_start(toy, cfg, f"p{i}") for i in range(2)]
    outs = [p.communicate(timeout=180)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert counter.read_text().count("computed") == 1
    summaries = [json.loads((toy.root / f"p{i}" / "summary.json").read_text()) for i in range(2)]
    assert sorted(s["stages"]["a"]["hit"] for s in summaries) == [False, True]
    assert summaries[0]["stages"]["a"]["key"] == summaries[1]["stages"]["a"]["key"]
    assert any("computed meanwhile by a concurrent pipeline" in o for o in outs)


TOY_ROOT_CONFIG = """
defaults:
  - _self_
seed: 7
profile_name: toy
alpha: {{value: 3, fail: false, sleep: 0, counter: ""}}
beta: {{offset: 10}}
gamma: {{x: 1}}
tracking: {{uri: "{uri}", experiment: cli, require_server: false}}
pipeline:
  cache_dir: cache
  force: []
  until: null
  stages:
    a: {{run: "{pkg}.alpha.stage:run", inputs: [], config: [alpha, seed]}}
    b: {{run: "{pkg}.beta.stage:run", inputs: [a], config: [beta]}}
hydra:
  job: {{chdir: false}}
  run: {{dir: "runs/${{now:%H-%M-%S-%f}}"}}
"""


@pytest.mark.slow
def test_cli_runs_hydra_app_with_tracking_worker_and_rerun_is_up_to_date(toy):
    conf = toy.root / "conf"
    conf.mkdir()
    (conf / "toy.yaml").write_text(TOY_ROOT_CONFIG.format(uri=toy.db_uri, pkg=toy.package))
    cmd = [sys.executable, "-m", "pipeline", "--config-path", str(conf), "--config-name", "toy", "beta.offset=5"]
    # A bad stage name fails before any stage runs or any MLflow run starts: it can start beside the first run.
    bad = subprocess.Popen(cmd + ["pipeline.until=zeta"], cwd=toy.root, env=_env(toy), stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    first = subprocess.run(cmd, cwd=toy.root, env=_env(toy), capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stdout + first.stderr
    second = subprocess.run(cmd, cwd=toy.root, env=_env(toy), capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "Stage 'b' didn't change, skipping" in second.stdout
    assert second.stdout.rstrip().endswith("Pipeline up to date.")
    summaries = sorted((toy.root / "runs").glob("*/summary.json"))
    assert len(summaries) == 2, "summary.json goes to Hydra's run directory; Hydra must not chdir"
    last = json.loads(summaries[-1].read_text())
    assert last["up_to_date"] and last["stages"]["b"]["metrics"] == {"beta.sum": 11.0}
    mlflow.set_tracking_uri(toy.db_uri)
    parent = mlflow.get_run(last["mlflow_run_id"])
    assert parent.info.run_name == "toy beta.offset=5"
    assert parent.data.params["beta.offset"] == "5" and parent.info.status == "FINISHED"

    _, bad_stderr = bad.communicate(timeout=120)
    assert bad.returncode == 1 and "error: pipeline.until: unknown stage(s) ['zeta']" in bad_stderr


# The CLI in a process that, at exit, lists the heavy modules it imported and the commands it started.
WATCHED_CLI = """
import atexit, json, subprocess, sys
started = []
_popen_init = subprocess.Popen.__init__
def _recording_init(self, args, *a, **k):
    started.append([str(x) for x in args] if isinstance(args, (list, tuple)) else [str(args)])
    _popen_init(self, args, *a, **k)
subprocess.Popen.__init__ = _recording_init
package, report = sys.argv[1:3]
def _report():
    heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("mlflow", "torch", "lightning", "sqlalchemy")
                   or m.startswith(package))
    with open(report, "w") as f:
        json.dump({"modules": heavy, "started": started}, f)
atexit.register(_report)
sys.argv = ["pipeline", *sys.argv[3:]]
from pipeline.cli import main
main()
"""


@pytest.mark.slow
def test_an_all_hit_rerun_already_recorded_imports_no_mlflow_and_no_stage_code(toy):
    conf = toy.root / "conf"
    conf.mkdir()
    (conf / "toy.yaml").write_text(TOY_ROOT_CONFIG.format(uri=toy.db_uri, pkg=toy.package))
    args = ["--config-path", str(conf), "--config-name", "toy"]

    def cli(name):
        report = toy.root / f"{name}.json"
        done = subprocess.run([sys.executable, "-c", WATCHED_CLI, toy.package, str(report), *args], cwd=toy.root,
                              env=_env(toy), capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout, json.loads(report.read_text())

    first_out, first = cli("first")
    assert any(m.startswith(toy.package) for m in first["modules"]), "the first run computes: stage code imported"
    assert any("pipeline.mlflow_worker" in c for c in first["started"]), "and logs through the tracking worker"
    again_out, again = cli("again")
    assert again["modules"] == [], again["modules"]
    assert not any("pipeline.mlflow_worker" in c for c in again["started"]), again["started"]
    first_summary, again_summary = sorted((toy.root / "runs").glob("*/summary.json"))
    recorded = json.loads(first_summary.read_text())["mlflow_run_id"]
    assert json.loads(again_summary.read_text())["mlflow_run_id"] == recorded
    assert f"Already recorded: MLflow run {recorded} " in again_out
    mlflow.set_tracking_uri(toy.db_uri)
    assert len(mlflow.search_runs(experiment_names=["cli"], output_format="list")) == 3  # the parent and a, b


def _square(x: int) -> int:
    return x * x


def _pool_in_a_sweep_job() -> list[int]:
    """What a sweep job does: reset the start method as the CLI does, then run a spawned process pool."""
    import multiprocessing as mp

    from pipeline.cli import spawnable_start_method

    spawnable_start_method()
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.map_async(_square, [2, 3]).get(timeout=60)


def test_a_sweep_job_in_a_loky_worker_can_start_a_process_pool():
    """`make ablations` runs its jobs in joblib's loky workers (the parallel launcher); the data stage
    renders with a spawned process pool there. Without the reset the pool's workers die at start."""
    from joblib.externals.loky import get_reusable_executor

    executor = get_reusable_executor(max_workers=1)
    try:
        assert executor.submit(_pool_in_a_sweep_job).result(timeout=120) == [4, 9]
    finally:
        executor.shutdown(wait=True, kill_workers=True)
