"""The content-addressed stage cache (docs/design.md §8).

Layout under the cache directory::

    <stage>/<key>/manifest.json     key parts, metrics, seconds, MLflow run id, output file record
    <stage>/<key>/out/              the stage's outputs (what downstream stages receive)
    <stage>/latest.json             the key parts of the stage's last run, to explain the next miss
    <stage>/.partial-<key>/         an entry being computed (never looks complete: no final name); kept
                                    across a crash so the next attempt at the key resumes from it
    <stage>/.trash-<key>-<pid>-<rnd> an entry being replaced
    <stage>/.locks/<key>.lock       fcntl lock: one computation per key across processes
    .code_imports.json              the import lists of the source files the plans hashed, by content hash
                                    (pipeline.codeversion): a memo, never part of a key

An entry exists under its final name only after the engine has written its manifest and renamed the
work directory into place, so a crash leaves at most a ``.partial-`` directory. Its name is stable so
that the next attempt at the same key (under the key's lock) gets the same ``out/`` back, with whatever
the crashed attempt left there (Lightning's ``last.ckpt``, cached crops): training resumes instead of
starting over. A stage that raises has its work directory removed: only crashes and interruptions
leave one behind.

Verification on read (``verify``):
- ``fast`` (default): the file list and every size must match the manifest; a file whose mtime differs
  from the manifest is re-hashed; small files (<= 1 MiB each, in path order, up to 8 MiB in total) are
  always re-hashed. So edits, truncation, deletions and additions are caught without reading a
  9,000-image dataset on every no-op run; only a same-size edit of a large file that also restores its
  mtime escapes, which ``full`` catches.
- ``full``: every file's content hash is checked.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import secrets
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import PipelineError


def replace_text_best_effort(path: Path, text: str) -> None:
    """Atomically replace ``path`` with ``text`` (a temporary file beside it, then a rename); a failure (a read-only
    cache, a full disk) leaves the old file and no temporary one behind, and is not raised: for records whose loss
    costs only an explanation or a re-computation."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()

MANIFEST = "manifest.json"
PARTIAL = ".partial-"
OUT = "out"
LATEST = "latest.json"
IMPORTS_MEMO = ".code_imports.json"
VERIFY_MODES = ("fast", "full")
SMALL_FILE_BYTES = 1 << 20
SMALL_FILES_BUDGET = 8 << 20


@dataclass(frozen=True)
class Entry:
    """A complete, verified cache entry."""

    path: Path
    manifest: dict

    @property
    def out_dir(self) -> Path:
        return self.path / OUT


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _walk_files(root: Path) -> dict[str, os.stat_result]:
    found: dict[str, os.stat_result] = {}
    for dirpath, _dirnames, filenames in os.walk(root):
        for name in filenames:
            full = os.path.join(dirpath, name)
            found[os.path.relpath(full, root).replace(os.sep, "/")] = os.lstat(full)
    return found


def record_files(out_dir: Path) -> dict[str, dict]:
    """{relative path: {size, mtime_ns, sha256}} of every file a stage wrote."""
    return {
        rel: {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": file_sha256(out_dir / rel)}
        for rel, st in sorted(_walk_files(out_dir).items())
    }


def verify_files(out_dir: Path, recorded: dict[str, dict], mode: str) -> str | None:
    """None if ``out_dir`` matches the manifest record, else what is wrong."""
    actual = _walk_files(out_dir)
    missing = sorted(set(recorded) - set(actual))
    if missing:
        return f"file(s) missing: {', '.join(missing[:3])}"
    extra = sorted(set(actual) - set(recorded))
    if extra:
        return f"unexpected file(s): {', '.join(extra[:3])}"
    budget = SMALL_FILES_BUDGET
    for rel in sorted(recorded):
        want, st = recorded[rel], actual[rel]
        if st.st_size != want["size"]:
            return f"{rel}: size {st.st_size} != recorded {want['size']}"
        small = st.st_size <= SMALL_FILE_BYTES and st.st_size <= budget
        if small:
            budget -= st.st_size
        if mode == "full" or small or st.st_mtime_ns != want["mtime_ns"]:
            if file_sha256(out_dir / rel) != want["sha256"]:
                return f"{rel}: content differs from the recorded hash"
    return None


def _write_error(stage: str, where: Path, exc: OSError) -> PipelineError:
    hint = "the disk is full" if exc.errno == errno.ENOSPC else "the directory is read-only or not writable"
    return PipelineError(
        f"cannot write the cache entry of stage '{stage}' under {where}: {exc.strerror or exc} "
        f"(perhaps {hint}). Nothing was added to the cache; existing entries are unchanged."
    )


class Cache:
    """Entries of every stage under one root directory."""

    def __init__(self, root: Path):
        self.root = root

    def stage_dir(self, stage: str) -> Path:
        return self.root / stage

    def entry_dir(self, stage: str, key: str) -> Path:
        return self.stage_dir(stage) / key

    # -- reading -------------------------------------------------------------------------------

    def lookup(self, stage: str, key: str, mode: str) -> tuple[Entry | None, str | None]:
        """(entry, None) for a complete, verified entry; (None, why) for a present but bad one;
        (None, None) when there is none."""
        path = self.entry_dir(stage, key)
        try:
            manifest = json.loads((path / MANIFEST).read_text())
        except FileNotFoundError:
            return None, None
        except (OSError, ValueError) as exc:
            return None, f"unreadable manifest ({exc})"
        if not isinstance(manifest, dict) or manifest.get("key") != key or not isinstance(manifest.get("files"), dict):
            return None, "manifest does not describe this key"
        problem = verify_files(path / OUT, manifest["files"], mode)
        if problem:
            return None, problem
        return Entry(path, manifest), None

    def read_latest(self, stage: str) -> dict | None:
        try:
            latest = json.loads((self.stage_dir(stage) / LATEST).read_text())
        except (OSError, ValueError):
            return None
        return latest if isinstance(latest, dict) else None

    # -- writing -------------------------------------------------------------------------------

    def write_latest(self, stage: str, parts: dict) -> None:
        """Atomically replace ``latest.json`` (a best-effort record: failure only loses an explanation)."""
        replace_text_best_effort(self.stage_dir(stage) / LATEST, json.dumps(parts, indent=1, sort_keys=True))

    @contextlib.contextmanager
    def lock(self, stage: str, key: str, on_wait=None):
        """Hold the per-key lock; ``on_wait()`` is called once if another process holds it."""
        lock_dir = self.stage_dir(stage) / ".locks"
        try:
            lock_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(lock_dir / f"{key}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise _write_error(stage, lock_dir, exc) from exc
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if on_wait:
                    on_wait()
                fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # closing releases the flock

    def partial_dir(self, stage: str, key: str) -> Path:
        return self.stage_dir(stage) / f"{PARTIAL}{key}"

    def begin(self, stage: str, key: str) -> tuple[Path, bool]:
        """(work directory, resumed) for computing ``key``; hold the lock. The work directory's ``out/`` is
        empty unless an earlier attempt at this key crashed, in which case it holds what that attempt
        left (``resumed`` is True)."""
        self.remove_stale(stage, key)
        work = self.partial_dir(stage, key)
        try:
            (work / OUT).mkdir(parents=True, exist_ok=True)
            (work / MANIFEST).unlink(missing_ok=True)  # a crash between writing it and the rename
        except OSError as exc:
            raise _write_error(stage, self.stage_dir(stage), exc) from exc
        return work, any((work / OUT).iterdir())

    def commit(self, stage: str, key: str, tmp: Path, manifest: dict) -> Entry:
        """Record the outputs, write the manifest and rename ``tmp`` into place; hold the lock."""
        final = self.entry_dir(stage, key)
        trash = None
        try:
            manifest = {**manifest, "key": key, "files": record_files(tmp / OUT)}
            _write_manifest(tmp / MANIFEST, manifest)
            if final.exists():  # a forced or corrupted entry being replaced
                trash = final.with_name(f".trash-{key}-{os.getpid()}-{secrets.token_hex(4)}")
                os.rename(final, trash)
            os.rename(tmp, final)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            if trash is not None and not final.exists():
                with contextlib.suppress(OSError):
                    os.rename(trash, final)
            raise _write_error(stage, self.stage_dir(stage), exc) from exc
        if trash is not None:
            shutil.rmtree(trash, ignore_errors=True)
        return Entry(final, manifest)

    def abort(self, tmp: Path) -> None:
        shutil.rmtree(tmp, ignore_errors=True)

    # -- cleaning ------------------------------------------------------------------------------

    def remove_stale(self, stage: str, key: str) -> None:
        """Remove leftovers of interrupted replacements of ``key`` (caller holds its lock, so none is live)."""
        stage_dir = self.stage_dir(stage)
        if not stage_dir.is_dir():
            return
        for child in stage_dir.iterdir():
            if child.name.startswith(f".trash-{key}-"):
                shutil.rmtree(child, ignore_errors=True)

    def sweep(self, stage: str) -> int:
        """Remove trash dirs of crashed replacements whose key nobody is computing now; returns how many."""
        stage_dir = self.stage_dir(stage)
        if not stage_dir.is_dir():
            return 0
        removed = 0
        for child in list(stage_dir.iterdir()):
            if not child.name.startswith(".trash-"):  # never .partial-: resumable work of a crashed run
                continue
            key = child.name.split("-")[1]
            lock_path = stage_dir / ".locks" / f"{key}.lock"
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # being computed right now by another pipeline
            else:
                shutil.rmtree(child, ignore_errors=True)
                removed += 1
            finally:
                os.close(fd)
        return removed


def _write_manifest(path: Path, manifest: dict) -> None:
    with path.open("w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True, allow_nan=True)
        f.flush()
        os.fsync(f.fileno())


def now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")
