"""Ports on 127.0.0.1 for the tests that start servers (MLflow, PostgreSQL) or need a server that is not there.
``make test`` runs two tests at once (pytest-xdist), so a port that was free a moment ago may be another test's by
the time a server binds it."""

from __future__ import annotations

import contextlib
import socket


def free_port() -> int:
    """A port on 127.0.0.1 that was free a moment ago. Free, not reserved: a server started on it can lose it to
    another test's server (pytest-xdist runs two tests at once), so the servers here retry on "address in use"."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def refused_port():
    """A port on 127.0.0.1 that refuses every connection while the block runs: bound without ``SO_REUSEADDR`` and
    never listening, so no server of another test can take it (a port from ``free_port`` could be)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def address_in_use(log: str) -> bool:
    """Whether a server's log says it could not bind its port (as uvicorn, which ``mlflow server`` and ``mlflow ui``
    run on, and PostgreSQL say it)."""
    return "address already in use" in log.lower()


@contextlib.contextmanager
def taken_port():
    """A port on 127.0.0.1 held by a listener of the test's own while the block runs, bound as uvicorn binds
    (``SO_REUSEADDR``): what another test's server holds when a server started on it finds it taken."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]
