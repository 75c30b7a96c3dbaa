"""Cluster paths: the pinned Hydra launcher plugins compose with the project's configs, and (slow) a
pipeline launched by ``torchrun`` with two ranks trains the relation network with Lightning's ``ddp``
while rank 0 alone plans, tracks and writes the cache. The submitit sweep itself is in test_sweeps.py, the
PostgreSQL tracking server in test_tracking_server.py."""

from __future__ import annotations

import os
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from packaging.requirements import Requirement

from tests.experiments.pipeline_runs import CONF, REPO, TINY, relation_runs_of_a_ddp_launch


def _pinned(package: str) -> str:
    import tomllib

    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    (spec,) = [Requirement(d).specifier for d in deps if Requirement(d).name == package]
    return str(spec)


@pytest.mark.parametrize("plugin", ["hydra-joblib-launcher", "hydra-submitit-launcher"])
def test_launcher_plugins_are_installed_at_the_pinned_version(plugin):
    # Their classifiers stop at Python 3.10: the version tested here is the one the project pins exactly.
    assert _pinned(plugin) == f"=={version(plugin)}"


@pytest.mark.parametrize(("launcher", "target"), [
    ("submitit_slurm", "SlurmLauncher"), ("submitit_local", "LocalLauncher"), ("local_parallel", "JoblibLauncher"),
])
def test_sweep_launchers_compose_with_the_paper_experiments(launcher, target):
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
            cfg = compose("config", overrides=["experiment=table1", f"hydra/launcher={launcher}"],
                          return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    assert cfg.hydra.launcher._target_.endswith(target)
    assert cfg.hydra.mode.name == "MULTIRUN" and dict(cfg.hydra.sweeper.params) == {"relation/backbone": "conv_fc,resnet18"}
    if launcher.startswith("submitit"):
        # submitit's job folders land inside the sweep directory, next to the jobs' own outputs
        assert cfg.hydra.launcher.submitit_folder == f"{cfg.hydra.sweep.dir}/.submitit/%j"


@pytest.mark.slow
def test_torchrun_two_ranks_train_relation_with_ddp_and_rank_zero_alone_records_it(smoke_store, tmp_path):
    """What `srun` does on a SLURM allocation, on one machine: torchrun starts the pipeline twice (gloo, CPU).
    Data and priors are the shared smoke run's entries; the relation network trains on both ranks."""
    import torch

    from tests.sqlite_store import fresh_store

    cache = smoke_store["dir"] / "cache"
    before = {p for p in cache.rglob("*")}
    uri = fresh_store(tmp_path / "mlflow.db")
    torchrun = Path(sys.executable).parent / "torchrun"
    # patience=6: a relation key of its own (test_ddp trains the same trainer config with patience 5)
    args = [str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "pipeline", *TINY, "trainer=ddp",
            "trainer.accelerator=cpu", "trainer.devices=2", "relation.train.epochs=2", "relation.train.patience=6",
            "pipeline.until=relation", f"pipeline.cache_dir={cache}", f"tracking.uri={uri}",
            f"hydra.run.dir={tmp_path / 'run'}"]
    env = {**os.environ, "DEEPWORD_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    done = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-6000:]
    assert "Starting with 2 processes" in log and "distributed_backend=gloo" in log
    assert "rank 1 of 2" in log and "joining stage 'relation'" in log
    # every rank checked its weights against the others' (a difference fails the stage)
    assert "relation: the 2 ranks hold identical weights" in log

    relation, runs = relation_runs_of_a_ddp_launch(tmp_path / "run", uri, "only rank 0 tracks")
    assert sorted(r.info.run_name for r in runs if "mlflow.parentRunId" in r.data.tags) == ["data", "priors",
                                                                                              "relation"]

    # Rank 0 alone wrote the cache: the new entry, its lock and latest.json; no half-written or launch files.
    new = sorted(str(p.relative_to(cache)) for p in cache.rglob("*") if p not in before)
    key = relation["key"]
    assert all(n.startswith((f"relation/{key}", f"relation/.locks/{key}", ".launches")) for n in new), new
    assert not list((cache / ".launches").glob("*.json")) and not list((cache / "relation").glob(".partial-*"))
    weights = torch.load(Path(relation["output_dir"]) / "relation.pt", map_location="cpu", weights_only=True)
    assert weights and all(torch.isfinite(v).all() for v in weights.values() if v.is_floating_point())


def test_ci_entry_installs_postgresql_for_the_tracking_server_test():
    text = (REPO / ".ci" / "run").read_text()
    assert "install -y -qq postgresql" in text and text.index("postgresql") < text.rindex("make test")
