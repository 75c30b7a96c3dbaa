"""The tracking worker's protocol: posted calls (log, end) do not wait, and their errors still surface."""

import mlflow
import pytest

from pipeline.errors import PipelineError
from pipeline.tracker import WorkerTracker


def test_posted_calls_are_recorded_and_a_failed_one_is_raised_by_the_next_wait(toy):
    worker = WorkerTracker()
    try:
        worker.open(toy.db_uri, "worker")
        parent = worker.create_run("parent", {"profile": "toy"})
        child = worker.create_run("child", {"cache": "hit"}, parent)
        worker.log(child, metrics={"a.x": 1.5}, tags={"computed_by_run": "r0"})
        worker.end(child)
        worker.end("no-such-run")  # posted: nothing raised yet
        with pytest.raises(PipelineError, match="MLflow 'end' failed"):
            worker.flush()
        worker.log(parent, params={"seed": "7"})
        worker.end(parent)
        worker.flush()
    finally:
        worker.close()
    mlflow.set_tracking_uri(toy.db_uri)
    got = mlflow.get_run(child)
    assert got.data.metrics == {"a.x": 1.5} and got.info.status == "FINISHED"
    assert got.data.tags["mlflow.parentRunId"] == parent
    assert mlflow.get_run(parent).data.params == {"seed": "7"}


def test_a_store_that_cannot_open_is_reported_by_the_first_run(tmp_path):
    worker = WorkerTracker()
    try:
        worker.open(f"sqlite:///{tmp_path}/missing/dir/mlflow.db", "worker")
        with pytest.raises(PipelineError, match="cannot open MLflow tracking store 'sqlite:///.*missing"):
            worker.create_run("parent", {})
    finally:
        worker.close()
