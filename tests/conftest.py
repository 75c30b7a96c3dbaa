"""Fixtures for every test directory. Every test folder is a package (``tests.stages.export`` ...), so helper
modules import by their full name and no folder's names shadow another's or the project's."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.sqlite_store import template


@pytest.fixture(scope="session")
def mlflow_template() -> Path:
    """An initialised empty MLflow sqlite store, to copy (never to write to)."""
    return template()
