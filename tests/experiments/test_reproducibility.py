"""Same seed, same metrics; another seed, other metrics. Separate caches, so nothing is shared but the
code and the config; every MLflow run (parent and stage children) records the seed and the git commit."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.experiments.pipeline_runs import REPO, TINY, finish_pipeline, start_pipeline

pytestmark = pytest.mark.slow

# Wall-clock figures differ between any two runs; everything else must not.
TIMING = (".seconds", "_seconds", "ms_per_", "ms_b", "speedup")


def _deterministic(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if not any(t in k for t in TIMING)}


def _stage_metrics(run_dir, stages) -> dict:
    summary = json.loads((run_dir / "summary.json").read_text())
    return {k: v for s in stages for k, v in _deterministic(summary["stages"][s]["metrics"]).items()}


def test_same_seed_same_metrics_other_seed_other_metrics(smoke_store, tmp_path):
    stages = ("data", "priors", "relation")
    again, other = tmp_path / "again", tmp_path / "other"
    # Independent runs (own cache, own store) side by side: each computes on one thread, CI has two cores.
    jobs = [start_pipeline(again, [*TINY, "pipeline.until=relation"], f"sqlite:///{again / 'mlflow.db'}"),
            start_pipeline(other, [*TINY, "seed=7", "pipeline.until=priors"], f"sqlite:///{other / 'mlflow.db'}")]
    for job in jobs:
        finish_pipeline(job)
    first = _stage_metrics(smoke_store["dir"] / "run", stages)
    second = _stage_metrics(again / "run", stages)
    assert any(k.startswith("relation.val.") for k in first)
    assert first == second

    changed = _stage_metrics(other / "run", ("data", "priors"))
    assert changed != {k: v for k, v in first.items() if k.split(".")[0] in ("data", "priors")}


def test_every_run_records_seed_and_git_commit(smoke_store):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(smoke_store["uri"])
    runs = client.search_runs([client.get_experiment_by_name("deepword").experiment_id])
    assert len(runs) == 10  # the parent and its nine stages
    for run in runs:
        assert run.data.tags["seed"] == "42", run.info.run_name
        commit = run.data.tags["git_commit"]
        assert len(commit) == 40 and subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"],
                                                    cwd=REPO).returncode == 0, commit
    (parent,) = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert parent.data.params["seed"] == "42"
