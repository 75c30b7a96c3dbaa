"""Fixtures for every test directory. Importing this file (pytest does, before the conftest files below
it) also puts tests/ on sys.path, so that shared helper modules here (sqlite_store) import by name."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlite_store import template


@pytest.fixture(scope="session")
def mlflow_template() -> Path:
    """An initialised empty MLflow sqlite store, to copy (never to write to)."""
    return template()
