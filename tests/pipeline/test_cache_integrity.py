"""Atomic entries: failures leave nothing that looks complete; tampering is detected; write errors are clear."""

import errno
import os
from pathlib import Path

import pytest

import pipeline.cache
from pipeline.errors import PipelineError
from pipeline.runner import run_pipeline


def run(toy, cfg):
    return run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)


def complete_entries(cache: Path, stage: str) -> list[Path]:
    stage_dir = cache / stage
    if not stage_dir.is_dir():
        return []
    return [p for p in stage_dir.iterdir() if not p.name.startswith(".") and p.is_dir()]


def test_stage_raising_leaves_no_entry_and_no_temp_and_rerun_computes(toy):
    with pytest.raises(RuntimeError, match="alpha failed on purpose"):
        run(toy, toy.config(**{"alpha.fail": True}))
    cache = toy.root / "cache"
    assert complete_entries(cache, "a") == []
    assert not [p for p in (cache / "a").iterdir() if p.name.startswith((".tmp-", ".partial-"))]
    summary = run(toy, toy.config())
    assert summary["stages"]["a"]["hit"] is False
    assert len(complete_entries(cache, "a")) == 1


def test_tampered_entry_is_detected_and_recomputed(toy, capsys):
    first = run(toy, toy.config())
    out_dir = Path(first["stages"]["a"]["output_dir"])
    (out_dir / "value.txt").write_text("7")  # same size: only the content hash can tell
    capsys.readouterr()
    second = run(toy, toy.config())
    out = capsys.readouterr().out
    assert second["stages"]["a"]["hit"] is False
    assert "entry corrupted (value.txt: content differs from the recorded hash)" in out
    assert (out_dir / "value.txt").read_text() == "6"
    assert second["stages"]["b"]["hit"] is True


def test_same_size_tamper_with_restored_mtime_is_caught(toy):
    first = run(toy, toy.config())
    target = Path(first["stages"]["b"]["output_dir"]) / "sum.txt"
    st = target.stat()
    target.write_text("99")  # same length as "16"
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert run(toy, toy.config())["stages"]["b"]["hit"] is False, "small files are always re-hashed"


def test_deleted_or_added_file_is_detected(toy):
    first = run(toy, toy.config())
    out_dir = Path(first["stages"]["c"]["output_dir"])
    (out_dir / "extra.txt").write_text("x")
    assert run(toy, toy.config())["stages"]["c"]["hit"] is False
    (out_dir / "g.txt").unlink()
    assert run(toy, toy.config())["stages"]["c"]["hit"] is False


@pytest.mark.parametrize("code, words", [(errno.ENOSPC, "disk is full"), (errno.EROFS, "read-only")])
def test_write_failure_gives_clear_error_and_leaves_cache_consistent(toy, monkeypatch, code, words):
    def failing_write(path, manifest):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(pipeline.cache, "_write_manifest", failing_write)
    with pytest.raises(PipelineError, match=f"cannot write the cache entry of stage 'a'.*{words}"):
        run(toy, toy.config())
    stage_dir = toy.root / "cache" / "a"
    assert complete_entries(toy.root / "cache", "a") == []
    assert not [p for p in stage_dir.iterdir() if p.name.startswith((".tmp-", ".partial-"))]
    monkeypatch.undo()
    monkeypatch.chdir(toy.root)
    assert run(toy, toy.config())["stages"]["a"]["hit"] is False


def test_unwritable_cache_dir_is_a_clear_error(toy):
    (toy.root / "blocker").write_text("a file where the cache directory should be")
    with pytest.raises(PipelineError, match="cannot write the cache entry of stage 'a'"):
        run(toy, toy.config(**{"pipeline.cache_dir": "blocker/cache"}))


def test_full_verify_mode_is_accepted_and_unknown_mode_rejected(toy):
    run(toy, toy.config())
    assert all(s["hit"] for s in run(toy, toy.config(**{"pipeline.verify": "full"}))["stages"].values())
    with pytest.raises(PipelineError, match="pipeline.verify"):
        run(toy, toy.config(**{"pipeline.verify": "sometimes"}))
