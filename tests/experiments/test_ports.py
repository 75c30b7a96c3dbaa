"""The test servers' ports under two test processes: a refused port stays refused. (An MLflow server that loses its
port to another server starts again on another one: the tracking-server test's server is started that way,
tests/experiments/test_tracking_server.py.)"""

from __future__ import annotations

import socket

import pytest

from tests.ports import refused_port


def test_a_refused_port_refuses_connections_and_cannot_be_taken_by_a_server():
    with refused_port() as port:
        with socket.socket() as client, pytest.raises(ConnectionRefusedError):
            client.connect(("127.0.0.1", port))
        with socket.socket() as server, pytest.raises(OSError, match="in use"):
            server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            server.bind(("127.0.0.1", port))
