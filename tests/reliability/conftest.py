"""Shared fixtures: the tiny WORD dataset and one MLflow store for the in-process pipeline runs."""

from __future__ import annotations

import pytest
from sqlite_store import fresh_store
from tiny_dataset import write_tiny_dataset


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="session")
def tracking_uri(tmp_path_factory):
    """One sqlite store for all in-process runs (copied from the session's initialised template)."""
    return fresh_store(tmp_path_factory.mktemp("mlflow") / "mlflow.db")
