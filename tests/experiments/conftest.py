"""Fixtures of the experiment tests: the shared smoke pipeline run (helpers: ``pipeline_runs``)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest

from tests.experiments.pipeline_runs import TINY, finish_pipeline, start_pipeline

# The shared smoke run (see ``smoke_store``), started by ``pytest_collection_modifyitems``.
_smoke: dict = {}


def _start_smoke(tmp: Path) -> None:
    db = tmp / "mlflow.db"
    _smoke.update(uri=f"sqlite:///{db}", dir=tmp, db=db)
    _smoke["job"] = start_pipeline(tmp, TINY, _smoke["uri"])


def _reads_smoke_store(item) -> bool:
    return "smoke_store" in getattr(item, "fixturenames", ())


def pytest_itemcollected(item):
    """The tests that read the shared smoke store form one group: with pytest-xdist's ``--dist loadgroup``
    (``make test``) they all run in one worker, so the store's pipeline runs once."""
    if _reads_smoke_store(item):
        item.add_marker(pytest.mark.xdist_group("smoke_store"))


@pytest.hookimpl(trylast=True)  # after -k/-m deselection: start the run only for tests that will run
def pytest_collection_modifyitems(config, items):
    """When a selected test reads the shared smoke store, start its pipeline run now, in the background,
    and move those tests to the end of the session: the run (one thread) overlaps every other test instead
    of the session waiting for it (CI has two cores). The tests keep their order among themselves. In an
    xdist worker nothing starts here: every worker collects every test, and only the one handed the group
    needs the run, which ``smoke_store`` then starts."""
    readers = [item for item in items if _reads_smoke_store(item)]
    if not readers or config.option.collectonly or hasattr(config, "workerinput"):
        return
    items[:] = [item for item in items if item not in readers] + readers
    tmp = Path(tempfile.mkdtemp(prefix="smoke_run_"))
    _start_smoke(tmp)
    config.add_cleanup(lambda: _stop_smoke(tmp))


def _stop_smoke(tmp: Path) -> None:
    if _smoke["job"].proc.poll() is None:  # the session ended early (a failure with -x, ctrl-c)
        _smoke["job"].proc.kill()
        _smoke["job"].proc.wait()
    shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture(scope="session")
def smoke_store(tmp_path_factory) -> dict:
    """One whole tiny smoke pipeline run (every stage), shared by the tests that read a real store:
    {"uri", "dir", "db"}. Started at collection (see above); here the session waits for it to finish."""
    if not _smoke:  # not started at collection (a test that reaches the fixture another way)
        _start_smoke(tmp_path_factory.mktemp("smoke_run"))
    finish_pipeline(_smoke["job"])
    return {k: _smoke[k] for k in ("uri", "dir", "db")}
