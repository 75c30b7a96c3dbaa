"""Whole pipelines as subprocesses under faults: SIGKILL in the middle of training, two pipelines on one
cache, a bad dataset through the CLI, images without vehicles or wheels through every stage."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.reliability.harness import complete_entries, copy_upstream, pipeline_command, pipeline_env
from tests.reliability.make_corpus import CORPUS
from tests.reliability.tiny_dataset import write_tiny_dataset

pytestmark = pytest.mark.slow


def run(tmp: Path, data: Path, *extra: str, timeout: int = 400) -> subprocess.CompletedProcess:
    return subprocess.run(pipeline_command(data, tmp / "cache", *extra), cwd=tmp, env=pipeline_env(tmp),
                          capture_output=True, text=True, timeout=timeout)


def wait_for(predicate, timeout: float, proc: subprocess.Popen, log: Path):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = predicate()
        if found:
            return found
        if proc.poll() is not None:
            pytest.fail(f"pipeline ended (rc {proc.returncode}) before the awaited state:\n{log.read_text()[-3000:]}")
        time.sleep(0.05)
    pytest.fail(f"timed out waiting; log:\n{log.read_text()[-3000:]}")


def frozen_with_checkpoint(pattern: str, root: Path, proc: subprocess.Popen):
    """A predicate for ``wait_for``: once a file matching ``pattern`` exists, stop the pipeline's process
    group (SIGSTOP) and return the file if it loads as a whole checkpoint, else let the group go on. A
    frozen pipeline cannot rewrite the checkpoint between the check and the kill, however short its epochs
    (a size-stable-for-0.2 s check never held on a host where the tiny dataset's epochs take 70 ms)."""
    import torch

    def check():
        for path in root.glob(pattern):
            os.killpg(proc.pid, signal.SIGSTOP)
            try:
                torch.load(path, map_location="cpu", weights_only=True)
                return path
            except Exception:  # caught mid-write: let it finish and look again
                os.killpg(proc.pid, signal.SIGCONT)
        return None
    return check


def test_sigkill_during_relation_training_leaves_no_entry_and_rerun_resumes_from_last_checkpoint(tmp_path, tiny,
                                                                                                  upstream):
    data = tiny
    copy_upstream(upstream[0], tmp_path / "cache")  # data and priors are hits: the kill is about relation
    # the pipeline is frozen as soon as a whole checkpoint exists (frozen_with_checkpoint), so the first member's
    # first epoch is enough to kill it mid-training: a few epochs leave the rest to resume
    extra = ["pipeline.until=relation", "relation.train.epochs=6", "relation.train.patience=100"]
    log = tmp_path / "killed.log"
    with log.open("w") as fh:
        proc = subprocess.Popen(pipeline_command(data, tmp_path / "cache", *extra), cwd=tmp_path,
                                env=pipeline_env(tmp_path), stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        # out/checkpoints for one network, out/members/<k>/checkpoints for an ensemble (the smoke profile's)
        ckpt = wait_for(frozen_with_checkpoint("relation/.partial-*/out/**/checkpoints/last.ckpt", tmp_path / "cache",
                                               proc), 300, proc, log)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert complete_entries(tmp_path / "cache", "relation") == []  # nothing that looks complete
    assert ckpt.is_file()  # the resumable state survived the crash

    rerun = run(tmp_path, data, *extra)
    out = rerun.stdout + rerun.stderr
    assert rerun.returncode == 0, out[-3000:]
    plan = rerun.stdout[: rerun.stdout.find("Running stage")]
    assert "Stage 'data' didn't change" in rerun.stdout and "Stage 'priors' didn't change" in rerun.stdout, plan
    assert "Stage 'relation': resuming from what an interrupted attempt left" in rerun.stdout
    assert "Restoring states from the checkpoint path at" in out and str(ckpt.name) in out
    entries = complete_entries(tmp_path / "cache", "relation")
    assert len(entries) == 1 and not list((tmp_path / "cache" / "relation").glob(".partial-*"))
    assert not (entries[0] / "out" / "checkpoints").exists() and not (entries[0] / "out" / "members").exists()


def test_two_pipelines_at_once_compute_each_stage_once_and_both_finish(tmp_path):
    data = write_tiny_dataset(tmp_path / "tiny")
    cmd = pipeline_command(data, tmp_path / "cache", "pipeline.until=priors")
    logs = [tmp_path / f"p{i}.log" for i in range(2)]
    procs = []
    for log in logs:
        with log.open("w") as fh:
            procs.append(subprocess.Popen(cmd, cwd=tmp_path, env=pipeline_env(tmp_path), stdout=fh,
                                          stderr=subprocess.STDOUT))
    for proc in procs:
        proc.wait(timeout=400)
    outs = [log.read_text() for log in logs]
    assert [p.returncode for p in procs] == [0, 0], outs[0][-2000:] + outs[1][-2000:]
    for stage in ("data", "priors"):
        assert sum(o.count(f"Running stage '{stage}'") for o in outs) == 1
        assert len(complete_entries(tmp_path / "cache", stage)) == 1


def test_bad_dataset_through_the_cli_is_one_clear_line_without_traceback(tmp_path):
    proc = run(tmp_path, CORPUS / "box_x2_lt_x1", "pipeline.until=priors", timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1
    assert "stage 'data' failed" in proc.stderr
    assert "labels.jsonl:2: field 'boxes[1]': x1 < x2 required" in proc.stderr
    assert "Traceback" not in out and 'File "' not in out
    assert complete_entries(tmp_path / "cache", "data") == []


def test_images_without_vehicles_or_wheels_flow_through_every_stage_with_defined_metrics(tmp_path):
    data = write_tiny_dataset(tmp_path / "tiny")
    # Export without registering the models and with a short latency measurement: neither depends on
    # what the images hold; every stage still computes on them.
    proc = run(tmp_path, data, "export.register=false", "export.latency.runs=2", "export.latency.images=4",
               timeout=600)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    import json
    summary = json.loads(next((tmp_path / "outputs").rglob("summary.json")).read_text())
    assert all(not s["hit"] for s in summary["stages"].values()) and "evaluate" in summary["stages"]
    metrics = {k: v for s in summary["stages"].values() for k, v in s["metrics"].items()}
    assert all(v == v for v in metrics.values()), [k for k, v in metrics.items() if v != v]  # no NaN
    assert any(k.startswith("eval.gt.") for k in metrics)
