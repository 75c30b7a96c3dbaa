"""The test servers' ports under two test processes: a refused port stays refused, and an MLflow server that
loses its port to another server starts again on another one."""

from __future__ import annotations

import socket

import pytest

from tests.experiments import pipeline_runs
from tests.ports import refused_port


def test_a_refused_port_refuses_connections_and_cannot_be_taken_by_a_server():
    with refused_port() as port:
        with socket.socket() as client, pytest.raises(ConnectionRefusedError):
            client.connect(("127.0.0.1", port))
        with socket.socket() as server, pytest.raises(OSError, match="in use"):
            server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            server.bind(("127.0.0.1", port))


@pytest.mark.slow
def test_mlflow_server_that_finds_its_port_taken_starts_again_on_another(tmp_path, monkeypatch):
    with socket.socket() as taken:
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        ports = iter([taken.getsockname()[1]])
        real_free_port = pipeline_runs.free_port
        monkeypatch.setattr(pipeline_runs, "free_port", lambda: next(ports, None) or real_free_port())
        server = pipeline_runs.MlflowServer(tmp_path, command="ui")
        try:
            server.wait_ready()
            assert server.port != taken.getsockname()[1]
            assert server.uri.endswith(f":{server.port}")
        finally:
            server.stop()
