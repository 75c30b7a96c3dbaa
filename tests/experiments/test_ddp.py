"""`trainer=ddp`: the relation network trained by Lightning DDP with 2 CPU processes (gloo), inside a real
pipeline run in a subprocess (the way users run it). Lightning's `ddp` starts rank 1 by re-running the
command; the rank-aware engine makes that process join the training and nothing else. Data and priors come
from the shared smoke run's cache; the relation stage is a miss because the trainer config is part of its
key. (torchrun: tests/experiments/test_clusters.py.)"""

from __future__ import annotations

import json

import pytest

from tests.experiments.pipeline_runs import TINY, relation_runs_of_a_ddp_launch, run_pipeline

pytestmark = pytest.mark.slow


def test_ddp_trains_relation_on_two_cpu_processes_logs_once_and_saves_loadable_weights(smoke_store, tmp_path):
    import torch
    from mlflow.tracking import MlflowClient

    db = tmp_path / "ddp.db"
    uri = f"sqlite:///{db}"
    proc = run_pipeline(tmp_path, [*TINY, "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2",
                                   "relation.train.epochs=2", "relation.train.patience=5", "pipeline.until=relation",
                                   # one network: the members and their student under DDP are test_clusters' torchrun
                                   "relation.ensemble=1"],
                        uri, cache=smoke_store["dir"] / "cache")
    log = proc.stdout + proc.stderr
    assert "distributed_backend=gloo" in log and "Starting with 2 processes" in log
    assert "local rank 1 of node 0" in log and "joining stage 'relation'" in log

    relation, runs = relation_runs_of_a_ddp_launch(tmp_path / "run", uri,
                                                   "a second rank must not start a pipeline run of its own")
    client = MlflowClient(uri)
    (child,) = [r for r in runs if r.info.run_name == "relation"]
    # Rank zero alone logs: one value per epoch (a second logging rank would double them).
    history = client.get_metric_history(child.info.run_id, "val/wheel_acc")
    assert sorted(m.step for m in history) == sorted({m.step for m in history}) and len(history) == 2
    assert child.data.metrics["relation.epochs"] == 2

    weights = torch.load(relation["output_dir"] + "/relation.pt", map_location="cpu", weights_only=True)
    assert weights and all(torch.isfinite(v).all() for v in weights.values() if v.is_floating_point())
    meta = json.loads(open(relation["output_dir"] + "/relation.json").read())
    assert len(meta["curves"]) == 2
