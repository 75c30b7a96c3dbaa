"""Helpers of the experiment tests: the real Hydra config composed with overrides, subprocess runs of the
pipeline on the smoke profile shrunk further (tiny data, a few training steps) into tmp dirs, and a real
MLflow server. (A module of its own, not conftest.py: test modules import from it, and ``conftest`` is one
module name for every test folder's conftest.)"""

from __future__ import annotations

import copy
import functools
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from pipeline.mlflow_ops import EXPERIMENT_KIND, EXPERIMENT_KIND_TAG
from pipeline.ui import NO_JOB_RUNNER
from tests.ports import address_in_use, free_port
from tests.sqlite_store import fresh_store, fresh_store_for_uri

REPO = Path(__file__).resolve().parents[2]
CONF = REPO / "conf"

# The smoke profile, smaller still: enough images for every split and subset, one short epoch each.
TINY = ["profile=smoke", "relation.train.limit_train_images=12",
        "relation.train.limit_val_images=8", "detector.limit_train_batches=1", "detector.limit_val_batches=1",
        "eval.gallery_images=2", "eval.fit_images=40", "export.register=false", "export.latency.runs=2",
        "export.latency.images=4", "export.parity.detector_images=2"]


def hydra_config(overrides: list[str]):
    """The composed ``hydra`` node (sweeper params, launcher, callbacks) for ``overrides``."""
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
            return compose("config", overrides=overrides, return_hydra_config=True).hydra
    finally:
        GlobalHydra.instance().clear()


def compose_config(overrides: list[str]) -> dict:
    """The resolved root config (a plain dict, the caller's own copy) for ``overrides``, as the pipeline would see
    it; composed once per test process (half a second to a second each, asked for again by many tests)."""
    return copy.deepcopy(_composed(tuple(overrides)))


@functools.cache
def _composed(overrides: tuple[str, ...]) -> dict:
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
            cfg = compose("config", overrides=list(overrides))
            return OmegaConf.to_container(cfg, resolve=True)
    finally:
        GlobalHydra.instance().clear()


def artifacts_beside_store(uri: str, artifacts: Path, experiment: str = "deepword") -> None:
    """Create the experiment with its artifacts under ``artifacts``: a sqlite store's default artifact
    root is ``./mlruns`` of the working directory, which would be the repository."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    if client.get_experiment_by_name(experiment) is None:
        client.create_experiment(experiment, artifact_location=artifacts.as_uri(),
                                 tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND})


@dataclass
class Started:
    """A pipeline subprocess and the files its stdout and stderr go to (files, not pipes: two pipelines
    run side by side must not block on a full pipe while the test waits for the other)."""
    proc: subprocess.Popen
    stdout: Path
    stderr: Path


def start_pipeline(tmp: Path, overrides: list[str], uri: str, cache: Path | None = None) -> Started:
    """``python -m pipeline`` started in a subprocess from the repo root, Hydra outputs, its output and
    (by default) the cache under ``tmp``; ``finish_pipeline`` waits for it."""
    tmp.mkdir(parents=True, exist_ok=True)
    if uri.startswith("sqlite:"):
        fresh_store_for_uri(uri)
        artifacts_beside_store(uri, tmp / "artifacts")
    args = [sys.executable, "-m", "pipeline", *overrides, f"pipeline.cache_dir={cache or tmp / 'cache'}",
            f"tracking.uri={uri}", f"hydra.run.dir={tmp / 'run'}", f"hydra.sweep.dir={tmp / 'sweep'}"]
    full_env = {**os.environ, "DEEPWORD_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    full_env.pop("MLFLOW_TRACKING_URI", None)
    started = Started(None, tmp / "pipeline.stdout", tmp / "pipeline.stderr")
    with started.stdout.open("w") as out, started.stderr.open("w") as err:
        started.proc = subprocess.Popen(args, cwd=REPO, env=full_env, stdout=out, stderr=err, text=True)
    return started


def finish_pipeline(started: Started, timeout: float = 600) -> subprocess.CompletedProcess:
    """Wait for a ``start_pipeline`` process; fail the test with its output tail unless it succeeded."""
    proc = started.proc
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    stdout, stderr = started.stdout.read_text(), started.stderr.read_text()
    if proc.returncode != 0:
        pytest.fail(f"pipeline {proc.args[3:]} failed ({proc.returncode}, timeout {timeout} s):\n"
                    f"{stdout[-3000:]}\n{stderr[-6000:]}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


def run_pipeline(tmp: Path, overrides: list[str], uri: str, timeout: float = 600,
                 cache: Path | None = None) -> subprocess.CompletedProcess:
    """``start_pipeline`` and wait for it."""
    return finish_pipeline(start_pipeline(tmp, overrides, uri, cache), timeout)


class MlflowServer:
    """A real ``mlflow server`` (or ``mlflow ui``) on 127.0.0.1 over a sqlite store (or ``backend_uri``), the
    artifact store in ``tmp`` proxied by the server; started in its own process group so that stopping it
    also stops its web workers."""

    def __init__(self, tmp: Path, command: str = "server", backend_uri: str | None = None):
        self.tmp, self.command = tmp, command
        self.backend_uri = backend_uri or fresh_store(tmp / "server.db")
        self.log = None
        self._start()

    def _start(self) -> None:
        self.port = free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        exe = Path(sys.executable).parent / "mlflow"
        args = [str(exe), self.command, "--host", "127.0.0.1", "--port", str(self.port),
                "--backend-store-uri", self.backend_uri, "--workers", "1"]
        if self.command == "server":
            args += ["--serve-artifacts", "--artifacts-destination", str(self.tmp / "artifacts")]
        if self.log is not None:
            self.log.close()
        self.log = (self.tmp / f"mlflow_{self.command}.log").open("w")
        # as ``make ui`` starts it: without MLflow's job runner (six more processes importing MLflow)
        env = {**os.environ, NO_JOB_RUNNER[0]: NO_JOB_RUNNER[1]}
        self.proc = subprocess.Popen(args, cwd=self.tmp, env=env, stdout=self.log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def wait_ready(self, timeout: float = 120) -> None:
        import time
        import urllib.request

        deadline, restarts = time.monotonic() + timeout, 0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                log = Path(self.log.name).read_text()
                if address_in_use(log) and restarts < 3:  # another test's server took the port first
                    restarts += 1
                    self._start()
                    continue
                raise RuntimeError(f"mlflow exited with {self.proc.returncode}: {log[-3000:]}")
            try:
                with urllib.request.urlopen(self.uri + "/health", timeout=2) as r:
                    if r.status == 200 and self.proc.poll() is None:  # ours answers, not another that holds the port
                        return
            except OSError:
                time.sleep(0.5)
        raise RuntimeError(f"mlflow not ready after {timeout} s: {Path(self.log.name).read_text()[-3000:]}")

    def stop(self) -> None:
        import signal

        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.log.close()


def relation_runs_of_a_ddp_launch(run_dir: Path, uri: str, one_parent_why: str) -> tuple[dict, list]:
    """The checks every multi-process launch of ``pipeline.until=relation`` on the shared smoke entries
    shares: data and priors hit, the relation trained its 2 epochs, and one parent run alone tracked the
    launch. Returns the relation stage's summary entry and the experiment's runs."""
    import json

    from mlflow.tracking import MlflowClient

    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stages"]["data"]["hit"] and summary["stages"]["priors"]["hit"]
    relation = summary["stages"]["relation"]
    assert not relation["hit"] and relation["metrics"]["relation.epochs"] == 2
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("deepword").experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(parents) == 1, one_parent_why
    return relation, runs
