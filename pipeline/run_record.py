"""Whether an all-hit re-run is already recorded in MLflow, found without importing MLflow.

A parent run carries the tag ``pipeline.run_digest``: a sha256 over everything the engine writes on it that
does not depend on timing: the run name, the experiment, the tags (profile, seed, git commit, overrides, config
choices, resolve-hook tags), the params (the flattened resolved config), every stage's cache key and the stages
left out. Two invocations with one digest record the same thing; the metrics of an all-hit run are the cache
entries' (their keys are in the digest), only the seconds differ.

When every stage is a hit and a FINISHED, not deleted parent run with the digest exists, the engine names that run
instead of logging a copy of it (docs/engine.md, "Tracking"). On a ``sqlite:///`` store the lookup reads the
store's ``runs``, ``tags`` and ``experiments`` tables with the standard library's sqlite3, read-only, in
milliseconds; MLflow itself is then never imported. Any other store, or a sqlite store this lookup cannot read,
answers ``UNKNOWN`` and the engine asks MLflow (``MlflowOps.find_recorded``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

DIGEST_TAG = "pipeline.run_digest"
PARENT_TAG = "mlflow.parentRunId"
STAGE_TAG = "stage"
UNKNOWN = "unknown"  # the lookup cannot tell: ask MLflow


@dataclass(frozen=True)
class RecordedRun:
    run_id: str
    name: str
    start_time: int  # milliseconds since the epoch
    children: dict[str, str] = field(default_factory=dict)  # stage -> its child run id

    def to_json(self) -> dict:
        return {"run_id": self.run_id, "name": self.name, "start_time": self.start_time, "children": self.children}

    @classmethod
    def from_json(cls, value: dict | None) -> RecordedRun | None:
        if not value:
            return None
        return cls(str(value["run_id"]), str(value["name"]), int(value["start_time"]), dict(value["children"]))


def run_digest(experiment: str, name: str, tags: dict[str, str], params: dict[str, str],
               stage_keys: dict[str, str], not_run: dict[str, str]) -> str:
    payload = {"experiment": experiment, "name": name, "tags": tags, "params": params, "stages": stage_keys,
               "not_run": not_run}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///path`` URI (relative paths from the current directory), else None."""
    if not uri.startswith("sqlite:///"):
        return None
    path = uri[len("sqlite:///"):].split("?", 1)[0]
    return Path(path) if path and path != ":memory:" else None


_FIND_PARENT = """
SELECT r.run_uuid, r.name, r.start_time FROM runs r JOIN tags t ON t.run_uuid = r.run_uuid
WHERE r.experiment_id = ? AND r.status = 'FINISHED' AND r.lifecycle_stage = 'active'
  AND t.key = ? AND t.value = ?
ORDER BY r.start_time DESC LIMIT 1
"""
_FIND_CHILDREN = """
SELECT s.value, p.run_uuid FROM tags p JOIN tags s ON s.run_uuid = p.run_uuid AND s.key = ?
WHERE p.key = ? AND p.value = ?
"""


def find_in_sqlite(uri: str, experiment: str, digest: str) -> RecordedRun | None | str:
    """The newest finished parent run tagged with ``digest`` in ``experiment``; None if there is none (or no store
    yet); ``UNKNOWN`` when ``uri`` is not a sqlite file or its tables cannot be read as expected."""
    path = sqlite_path(uri)
    if path is None:
        return UNKNOWN
    if not path.is_file():
        return None  # no store, so nothing recorded; MLflow creates it when the run is logged
    try:
        with contextlib.closing(sqlite3.connect(f"file:{path.resolve()}?mode=ro", uri=True, timeout=5)) as db:
            experiments = db.execute("SELECT experiment_id FROM experiments WHERE name = ? AND lifecycle_stage = "
                                     "'active'", (experiment,)).fetchall()
            if not experiments:
                return None
            if len(experiments) > 1:  # one name in several workspaces: which one MLflow opens is MLflow's call
                return UNKNOWN
            row = db.execute(_FIND_PARENT, (experiments[0][0], DIGEST_TAG, digest)).fetchone()
            if row is None:
                return None
            children = dict(db.execute(_FIND_CHILDREN, (STAGE_TAG, PARENT_TAG, row[0])).fetchall())
    except sqlite3.Error:
        return UNKNOWN  # another schema, a locked or damaged file: MLflow decides
    return RecordedRun(str(row[0]), str(row[1] or ""), int(row[2] or 0), {str(k): str(v) for k, v in children.items()})
