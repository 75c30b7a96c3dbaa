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


@pytest.hookimpl(trylast=True)  # after tests/experiments/conftest.py has grouped the smoke run's readers
def pytest_itemcollected(item):
    """Tests sharing a costly fixture built once per process form one xdist group (``make test``'s ``--dist
    loadgroup``), so the fixture is built once, not once in each worker: a module-scoped fixture groups its module,
    a session-scoped one of a folder's conftest groups that folder (a parent pipeline run, a trained detector, a
    generated dataset: 2-11 s each). Fixtures of pytest itself and of ``tests/conftest.py`` (a copied sqlite
    store) are cheap and group nothing."""
    if item.get_closest_marker("xdist_group") is not None:
        return
    info = getattr(item, "_fixtureinfo", None)
    homes = {fixture.baseid for defs in (info.name2fixturedefs.values() if info else ())
             for fixture in defs[-1:] if fixture.scope in ("module", "session")}
    homes -= {"", "tests"}
    if homes:
        item.add_marker(pytest.mark.xdist_group(min(homes, key=len)))  # the widest scope: one group covers both
