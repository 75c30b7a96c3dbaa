"""`tracking=server` for real: a `mlflow server` on 127.0.0.1 (artifact store in tmp, proxied by the server)
on the team setup's PostgreSQL (a throwaway cluster started by the test; a sqlite backend where PostgreSQL is not
installed), the smoke pipeline (data + priors) run against it in a subprocess, and the runs read back over HTTP.
The server's first port is taken by another listener, so it also shows that a test server which loses its port
starts again on another (``MlflowServer.wait_ready``)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.experiments import pipeline_runs
from tests.experiments.pipeline_runs import REPO, MlflowServer, run_pipeline
from tests.experiments.postgres_cluster import PostgresCluster, find_bin_dir
from tests.ports import refused_port, taken_port

pytestmark = pytest.mark.slow


@pytest.fixture()
def server(tmp_path, monkeypatch):
    """A tracking server on the team setup's PostgreSQL where its binaries are installed (CI's ``.ci/run`` installs
    them), on sqlite elsewhere. One backend is enough: the pipeline speaks only HTTP to the server, so what differs
    between backends is MLflow's server, not this project's code; a second server and pipeline run cost CI ~40 s.
    The first port the server is given is held by a listener of the test's own (as another test's server would hold
    it under two test processes): ``srv.lost_port`` is that port, and the server must be answering on another."""
    bin_dir = find_bin_dir()
    database = PostgresCluster(bin_dir) if bin_dir is not None else None
    with taken_port() as lost_port:
        ports = iter([lost_port])
        real_free_port = pipeline_runs.free_port
        monkeypatch.setattr(pipeline_runs, "free_port", lambda: next(ports, None) or real_free_port())
        try:
            if database is not None:
                database.start()
            srv = MlflowServer(tmp_path, backend_uri=database.uri if database else None)
            srv.database, srv.lost_port = database, lost_port
            try:
                srv.wait_ready()
                yield srv
            finally:
                srv.stop()
        finally:
            if database is not None:
                database.stop()


def test_pipeline_logs_parent_children_metrics_and_artifacts_to_a_tracking_server(server, tmp_path):
    assert server.port != server.lost_port and server.uri.endswith(f":{server.port}")
    # Half the smoke data (16 images, as the sweep test): what is checked is the logging, not the priors.
    proc = run_pipeline(tmp_path / "job", ["profile=smoke", "data.frames=4", "pipeline.until=priors",
                                           "tracking=server"], server.uri)
    assert "MLflow run" in proc.stdout

    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=server.uri)
    exp = client.get_experiment_by_name("deepword")
    assert exp is not None and exp.tags["mlflow.experimentKind"] == "custom_model_development"
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(parents) == 1
    parent = parents[0]
    children = {r.info.run_name: r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id}
    assert set(children) == {"data", "priors"}
    assert parent.data.tags["profile"] == "smoke" and parent.data.tags["seed"] == "42"
    assert parent.data.metrics["data.train.images"] > 0
    assert "priors.wheel_vehicle.components" in children["priors"].data.metrics
    assert parent.data.params["tracking.uri"] == server.uri

    # Artifacts went through the server into its artifact store (--artifacts-destination).
    listed = [a.path for a in client.list_artifacts(children["priors"].info.run_id)]
    png = next(p for p in listed if p.endswith(".png"))
    local = client.download_artifacts(children["priors"].info.run_id, png, str(tmp_path / "dl"))
    with open(local, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    stored = list((tmp_path / "artifacts").rglob(png.split("/")[-1]))
    assert stored, "the artifact is in the server's artifact store"

    if server.database is not None:  # the runs are rows of the PostgreSQL database, not of some other store
        import sqlalchemy

        engine = sqlalchemy.create_engine(server.database.uri)
        try:
            with engine.connect() as db:
                stored_runs = set(db.execute(sqlalchemy.text("SELECT run_uuid FROM runs")).scalars())
        finally:
            engine.dispose()
        assert {r.info.run_id for r in runs} == stored_runs


def test_unreachable_server_fails_before_any_stage(tmp_path):
    with refused_port() as port:
        proc = subprocess.run([sys.executable, "-m", "pipeline", "profile=smoke", "tracking=server",
                               f"tracking.uri=http://127.0.0.1:{port}", f"pipeline.cache_dir={tmp_path / 'cache'}",
                               f"hydra.run.dir={tmp_path / 'run'}"], cwd=REPO, capture_output=True, text=True,
                              timeout=120)
    assert proc.returncode == 1
    assert "is not reachable" in proc.stderr and "no stage was run" in proc.stderr
    assert not (tmp_path / "cache" / "data").exists()
