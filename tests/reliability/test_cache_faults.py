"""The cache under faults (docs/design.md §8, §10): a tampered entry is never used, a failed write leaves the
cache as it was, an unreachable tracking server stops the run before any stage. In-process, on a tiny
WORD dataset, stopping early (``pipeline.until``) to stay fast."""

from __future__ import annotations

import errno
import json
import os
import time

import pytest

from pipeline.errors import PipelineError
from tests.ports import refused_port
from tests.reliability.harness import complete_entries, run_in_process


def leftovers(cache, stage) -> list[str]:
    stage_dir = cache / stage
    return sorted(p.name for p in stage_dir.iterdir() if p.name.startswith((".tmp-", ".trash-", ".partial-"))) \
        if stage_dir.is_dir() else []


# (tests/pipeline covers deleted, added and truncated files on toy stages; here: the real data stage)
@pytest.mark.parametrize("tamper", ["edit", "manifest"])
def test_tampered_cache_entry_is_detected_on_read_and_recomputed(tmp_path, tiny, tracking_uri, tamper):
    cache = tmp_path / "cache"
    first = run_in_process(tiny, cache, tracking_uri, "pipeline.until=data")
    out = complete_entries(cache, "data")[0] / "out"
    splits = out / "splits.json"
    original = splits.read_bytes()
    if tamper == "edit":  # same size, same mtime: only the content hash can tell
        stat = splits.stat()
        splits.write_bytes(original.replace(b"images/front", b"images/frunt", 1))
        os.utime(splits, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    else:
        (out.parent / "manifest.json").write_text("{ not json")
    second = run_in_process(tiny, cache, tracking_uri, "pipeline.until=data")
    data = second["stages"]["data"]
    assert not data["hit"] and data["key"] == first["stages"]["data"]["key"]
    assert splits.read_bytes() == original
    third = run_in_process(tiny, cache, tracking_uri, "pipeline.until=data")
    assert third["stages"]["data"]["hit"] and leftovers(cache, "data") == []


def test_cache_write_failure_gives_clear_error_and_keeps_existing_entries(tmp_path, tiny, tracking_uri, monkeypatch):
    cache = tmp_path / "cache"
    run_in_process(tiny, cache, tracking_uri, "pipeline.until=data")
    data_entry = complete_entries(cache, "data")[0]
    manifest_before = (data_entry / "manifest.json").read_text()
    real_rename = os.rename

    def read_only_rename(src, dst):
        if "priors" in str(dst):
            raise OSError(errno.EROFS, "Read-only file system", str(dst))
        return real_rename(src, dst)

    monkeypatch.setattr(os, "rename", read_only_rename)
    with pytest.raises(PipelineError, match=r"cannot write the cache entry of stage 'priors'.*read-only"):
        run_in_process(tiny, cache, tracking_uri, "pipeline.until=priors")
    monkeypatch.setattr(os, "rename", real_rename)
    assert complete_entries(cache, "priors") == [] and leftovers(cache, "priors") == []
    assert (data_entry / "manifest.json").read_text() == manifest_before
    after = run_in_process(tiny, cache, tracking_uri, "pipeline.until=priors")
    assert after["stages"]["data"]["hit"] and not after["stages"]["priors"]["hit"]


def test_cache_dir_that_cannot_be_created_fails_with_clear_error(tmp_path, tiny, tracking_uri):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("a file where the cache directory should be")
    with pytest.raises(PipelineError, match="cannot write the cache entry of stage 'data'"):
        run_in_process(tiny, blocker / "cache", tracking_uri, "pipeline.until=data")


def test_unreachable_tracking_server_fails_fast_before_any_stage(tmp_path, tiny):
    cache = tmp_path / "cache"
    start = time.perf_counter()
    with refused_port() as port, pytest.raises(PipelineError, match="not reachable.*no stage was run"):
        run_in_process(tiny, cache, f"http://127.0.0.1:{port}", "tracking=server")
    assert time.perf_counter() - start < 15
    assert not cache.exists() or all(complete_entries(cache, s) == [] for s in ("data", "priors"))


def test_summary_records_the_entry_it_used(tmp_path, tiny, tracking_uri):
    summary = run_in_process(tiny, tmp_path / "cache", tracking_uri, "pipeline.until=data")
    manifest = json.loads((complete_entries(tmp_path / "cache", "data")[0] / "manifest.json").read_text())
    assert manifest["key"] == summary["stages"]["data"]["key"]
