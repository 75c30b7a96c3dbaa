"""Shared fixtures: the tiny WORD dataset, one MLflow store for the in-process pipeline runs, and a cache
holding the tiny dataset's data and priors entries."""

from __future__ import annotations

import pytest

from tests.reliability.harness import run_in_process
from tests.reliability.tiny_dataset import write_tiny_dataset
from tests.sqlite_store import fresh_store


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="session")
def tracking_uri(tmp_path_factory):
    """One sqlite store for all in-process runs (copied from the session's initialised template)."""
    return fresh_store(tmp_path_factory.mktemp("mlflow") / "mlflow.db")


@pytest.fixture(scope="session")
def upstream(tmp_path_factory, tiny, tracking_uri):
    """A cache holding data and priors for the tiny dataset, computed once: the relation tests start from
    it (in place, or from a copy: harness.copy_upstream); also their keys."""
    cache = tmp_path_factory.mktemp("upstream") / "cache"
    summary = run_in_process(tiny, cache, tracking_uri, "pipeline.until=priors")
    return cache, {s: summary["stages"][s]["key"] for s in ("data", "priors")}

