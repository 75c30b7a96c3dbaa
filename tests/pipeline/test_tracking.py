"""MLflow parent/child runs, summary.json, server fail-fast and the stage's view of its run."""

import json
import socket
import time
from pathlib import Path

import mlflow
import pytest

from pipeline.errors import PipelineError
from pipeline.run_record import DIGEST_TAG
from pipeline.runner import run_pipeline
from pipeline.tracker import flatten_params
from pipeline.tracking import stage_run_info


def runs(toy):
    mlflow.set_tracking_uri(toy.db_uri)
    return mlflow.search_runs(experiment_names=["toy"], output_format="list")


def test_parent_and_child_runs_carry_params_metrics_and_cache_tags(toy):
    first = run_pipeline(toy.config(), run_dir=toy.root / "run", in_process_tracking=True)
    # Another config that leaves every key as it was: all hits, and a run of its own (its params differ).
    second = run_pipeline(toy.config(**{"unrelated.knob": 2}), run_dir=toy.root / "run2", in_process_tracking=True)
    by_id = {r.info.run_id: r for r in runs(toy)}
    assert len(by_id) == 2 * 4
    assert second["up_to_date"] and not second["already_recorded"]

    parent = by_id[second["mlflow_run_id"]]
    assert parent.info.run_name == "toy"
    assert parent.data.tags["profile"] == "toy" and parent.data.tags["seed"] == "7"
    assert "git_commit" in parent.data.tags
    assert parent.data.params["alpha.value"] == "3" and parent.data.params["unrelated.knob"] == "2"
    assert parent.data.tags[DIGEST_TAG] != by_id[first["mlflow_run_id"]].data.tags[DIGEST_TAG]
    assert parent.data.params["pipeline.stages.a.config"] == '["alpha", "seed"]'
    assert parent.data.metrics["alpha.value"] == 6.0 and parent.data.metrics["beta.sum"] == 16.0
    assert {"a.seconds", "b.seconds", "c.seconds", "pipeline.seconds"} <= set(parent.data.metrics)

    computed = by_id[first["stages"]["a"]["mlflow_run_id"]]
    assert computed.data.tags["cache"] == "miss"
    assert computed.data.tags["mlflow.parentRunId"] == first["mlflow_run_id"]
    hit = by_id[second["stages"]["a"]["mlflow_run_id"]]
    assert hit.data.tags["cache"] == "hit"
    assert hit.data.tags["mlflow.parentRunId"] == second["mlflow_run_id"]
    assert hit.data.tags["computed_by_run"] == computed.info.run_id
    assert hit.data.tags["cache_key"] == second["stages"]["a"]["key"]
    assert hit.data.metrics["alpha.value"] == 6.0
    assert hit.info.status == "FINISHED"
    artifacts = mlflow.MlflowClient(toy.db_uri).list_artifacts(computed.info.run_id)
    assert [a.path for a in artifacts] == ["report.md"]


def test_an_all_hit_rerun_already_recorded_names_that_run_and_logs_nothing(toy, capsys):
    first = run_pipeline(toy.config(), run_dir=toy.root / "run", in_process_tracking=True)
    again = run_pipeline(toy.config(), run_dir=toy.root / "run2", in_process_tracking=True)
    assert len(runs(toy)) == 4, "no second parent run, no hit child runs"
    out = capsys.readouterr().out
    assert f"Already recorded: MLflow run {first['mlflow_run_id']} ('toy', started " in out
    assert out.rstrip().endswith("Pipeline up to date.")
    written = json.loads((toy.root / "run2" / "summary.json").read_text())
    assert written == json.loads(json.dumps(again))
    assert again["already_recorded"] and again["up_to_date"] and again["mlflow_run_id"] == first["mlflow_run_id"]
    for name, stage in again["stages"].items():  # each stage names the recorded run's child, which computed it
        assert stage["hit"] and stage["mlflow_run_id"] == first["stages"][name]["mlflow_run_id"]
        assert stage["computed_by_run"] == first["stages"][name]["mlflow_run_id"]
        assert stage["metrics"] == first["stages"][name]["metrics"] and stage["key"] == first["stages"][name]["key"]

    # The recorded run deleted in the UI, or a stage forced: logged again.
    mlflow.MlflowClient(toy.db_uri).delete_run(first["mlflow_run_id"])
    third = run_pipeline(toy.config(), run_dir=toy.root / "run3", in_process_tracking=True)
    assert not third["already_recorded"] and third["mlflow_run_id"] != first["mlflow_run_id"]
    forced = run_pipeline(toy.config(**{"pipeline.force": ["c"]}), run_dir=toy.root / "run4", in_process_tracking=True)
    assert not forced["already_recorded"] and not forced["up_to_date"]
    assert len(runs(toy)) == 3 + 4 + 4  # the deleted parent's children, then the third and forced runs


def test_a_store_the_engine_cannot_read_itself_is_asked_through_mlflow(toy, monkeypatch):
    import pipeline.runner as runner
    from pipeline.run_record import UNKNOWN

    first = run_pipeline(toy.config(), run_dir=toy.root / "run", in_process_tracking=True)
    monkeypatch.setattr(runner, "find_in_sqlite", lambda *args: UNKNOWN)
    again = run_pipeline(toy.config(), run_dir=toy.root / "run2", in_process_tracking=True)
    assert again["already_recorded"] and again["mlflow_run_id"] == first["mlflow_run_id"]
    assert {n: s["mlflow_run_id"] for n, s in again["stages"].items()} == {
        n: s["mlflow_run_id"] for n, s in first["stages"].items()}
    assert len(runs(toy)) == 4


def test_stage_sees_its_child_run_and_none_outside(toy):
    summary = run_pipeline(toy.config(), run_dir=toy.root / "run", in_process_tracking=True)
    seen = (Path(summary["stages"]["a"]["output_dir"]) / "run_info.txt").read_text()
    assert seen == repr((toy.db_uri, summary["stages"]["a"]["mlflow_run_id"]))
    assert stage_run_info() is None


def test_summary_json_lists_every_stage(toy):
    summary = run_pipeline(toy.config(), run_dir=toy.root / "run", in_process_tracking=True)
    written = json.loads((toy.root / "run" / "summary.json").read_text())
    assert written == json.loads(json.dumps(summary))
    assert set(written["stages"]) == {"a", "b", "c"}
    b = written["stages"]["b"]
    assert set(b) >= {"key", "hit", "seconds", "output_dir", "metrics", "mlflow_run_id"}
    assert Path(b["output_dir"], "sum.txt").read_text() == "16"
    assert written["mlflow_run_id"] and written["up_to_date"] is False


def test_unreachable_required_server_fails_fast_before_any_stage(toy):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here once closed
    counter = toy.root / "count.txt"
    cfg = toy.config(**{"tracking.uri": f"http://127.0.0.1:{port}", "tracking.require_server": True,
                        "alpha.counter": str(counter)})
    start = time.perf_counter()
    with pytest.raises(PipelineError, match=f"MLflow tracking server http://127.0.0.1:{port} is not reachable"):
        run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert time.perf_counter() - start < 5
    assert not counter.exists() and not (toy.root / "cache").exists()


def test_long_params_are_truncated_and_lists_are_json():
    flat = flatten_params({"a": {"b": "x" * 600, "c": [1, 2]}, "d": None})
    assert len(flat["a.b"]) == 500 and flat["a.b"].endswith("[truncated]")
    assert flat["a.c"] == "[1, 2]" and flat["d"] == "null"


def test_experiment_opens_on_training_runs_and_a_dataset_stage_is_the_runs_dataset_input(toy):
    from pipeline.mlflow_ops import EXPERIMENT_KIND, EXPERIMENT_KIND_TAG

    client = mlflow.MlflowClient(toy.db_uri)
    client.create_experiment("toy")  # made by another tool, without the kind: the engine adds it
    cfg = toy.config(**{"pipeline.stages.a.dataset": "toyset"})
    summary = run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    assert client.get_experiment_by_name("toy").tags[EXPERIMENT_KIND_TAG] == EXPERIMENT_KIND
    parent = client.get_run(summary["mlflow_run_id"])
    (logged,) = parent.inputs.dataset_inputs
    assert logged.dataset.name == "toyset"
    assert logged.dataset.digest == summary["stages"]["a"]["key"][:36]
    assert logged.dataset.source == str(Path(summary["stages"]["a"]["output_dir"]).resolve())
    stage_b = client.get_run(summary["stages"]["b"]["mlflow_run_id"])
    assert not stage_b.inputs.dataset_inputs  # only the parent run, only for the declared stage


def test_a_dataset_another_pipeline_inserted_meanwhile_is_linked_on_the_second_attempt(toy):
    """MLflow looks a dataset up and then inserts it; a concurrent pipeline can insert it in between."""
    from pipeline.mlflow_ops import MlflowOps

    ops = MlflowOps(toy.db_uri, "toy")
    run_id = ops.create_run("r", {})
    real, calls = ops.client.log_inputs, []

    def racing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("(sqlite3.IntegrityError) UNIQUE constraint failed: datasets.experiment_id")
        return real(*args, **kwargs)

    ops.client.log_inputs = racing
    ops.log_dataset(run_id, "toyset", "f" * 64, "/data")
    assert len(calls) == 2
    (logged,) = ops.client.get_run(run_id).inputs.dataset_inputs
    assert (logged.dataset.name, logged.dataset.digest) == ("toyset", "f" * 36)
    ops.client.log_inputs = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("disk I/O error"))
    with pytest.raises(RuntimeError, match="disk I/O error"):  # any other failure is not retried
        ops.log_dataset(run_id, "toyset", "e" * 64, "/data")
