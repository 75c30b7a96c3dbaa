"""``make ui`` (``python -m pipeline.ui``): what it executes. The UI itself in a browser: tests/experiments/test_mlflow_ui.py."""

from __future__ import annotations

import os

import pytest

from pipeline import ui
from tests.sqlite_store import fresh_store


class _Executed(Exception):
    pass


def _exec_of(monkeypatch, argv: list[str]) -> tuple[list[str], dict]:
    seen = {}

    def execv(path, args):
        seen.update(path=path, args=args, env=dict(os.environ))
        raise _Executed

    monkeypatch.setattr(os, "execv", execv)
    with pytest.raises(_Executed):
        ui.main(argv)
    assert seen["path"] == seen["args"][0] and seen["path"].endswith("mlflow")
    return seen["args"][1:], seen["env"]


def test_ui_serves_the_store_on_loopback_without_mlflows_job_runner(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", raising=False)
    uri = fresh_store(tmp_path / "mlflow.db")
    args, env = _exec_of(monkeypatch, ["--backend-store-uri", uri, "--port", "5123"])
    assert args == ["ui", "--backend-store-uri", uri, "--host", "127.0.0.1", "--port", "5123"]
    assert env["MLFLOW_SERVER_ENABLE_JOB_EXECUTION"] == "false"
    # no experiment yet: the address is the experiments list, in the model-training view
    assert "http://127.0.0.1:5123/#/experiments?workflowType=machine_learning" in capsys.readouterr().err


def test_a_job_runner_the_environment_asks_for_is_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "true")
    _, env = _exec_of(monkeypatch, ["--backend-store-uri", fresh_store(tmp_path / "mlflow.db")])
    assert env["MLFLOW_SERVER_ENABLE_JOB_EXECUTION"] == "true"
