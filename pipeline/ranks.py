"""Pipelines launched as several processes (torchrun, srun, Lightning's own ``ddp`` launcher): which process
this is, and how rank 0 tells the other ranks what it does.

Every rank runs the same command, so every rank composes the same config and computes the same plan. Rank 0
alone runs the pipeline as usual: it takes the cache locks, computes and commits entries and records the
run in MLflow. Every other rank writes nothing: it waits for rank 0 to reach each stage declared
``every_rank: true`` (a training stage whose processes form one DDP group) and, when rank 0 computes that
stage, calls the stage too, in a scratch directory that is deleted afterwards, then exits.

Rank 0 announces what it does in a small launch file in the cache, ``<cache>/.launches/<launch id>.json``,
rewritten atomically (only rank 0 writes it)::

    {"plan": {stage: key}, "computing": {stage: {"key": ..., "resumed": bool, "work_dir": ...}},
     "error": null | "why rank 0 stopped"}

A rank other than 0 joins stage S when the file lists S as computing under the key it planned itself; it
skips S when S's cache entry exists and the file does not list S. Both decisions agree with rank 0's:
rank 0 decides under the key's lock, and an entry cannot appear while rank 0 holds that lock unless rank 0
computes it, which it cannot finish without the other ranks. The launch id, shared by every rank, comes
from the launcher (torchrun's run id, SLURM's job and step); a process that starts the other ranks itself
(Lightning's ``ddp`` on one machine) passes its own through ``PIPELINE_LAUNCH_ID``.

Rank variables read, first found wins: ``RANK`` / ``WORLD_SIZE`` (torchrun, submitit's
``TorchDistributedEnvironment().export()``), ``SLURM_PROCID`` / ``SLURM_NTASKS`` (srun), ``NODE_RANK`` /
``LOCAL_RANK`` (Lightning's launcher).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import PipelineError

LAUNCH_ID_VARIABLE = "PIPELINE_LAUNCH_ID"
LAUNCHES_DIR = ".launches"
STALE_LAUNCH_SECONDS = 7 * 24 * 3600  # launch files of failed launches are kept this long, for inspection
POLL_SECONDS = 0.5


@dataclass(frozen=True)
class Rank:
    """This process's place in its launch: ``index`` 0 for rank 0 and for a pipeline launched alone."""

    index: int
    world_size: int
    launch_id: str | None  # the same on every rank of a launch; None when the launcher gives none
    described: str  # "rank 1 of 2", for messages

    @property
    def is_zero(self) -> bool:
        return self.index == 0


def _int(environ, name: str) -> int | None:
    value = environ.get(name)
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError:
        raise PipelineError(f"environment variable {name}={value!r}: expected an integer") from None


def _launcher_launch_id(environ) -> str | None:
    if environ.get(LAUNCH_ID_VARIABLE):
        return environ[LAUNCH_ID_VARIABLE]
    run_id = environ.get("TORCHELASTIC_RUN_ID")
    if run_id and run_id != "none":
        return f"torchrun-{run_id}"
    if environ.get("SLURM_JOB_ID"):
        step = environ.get("SLURM_STEP_ID", "batch")
        restart = environ.get("SLURM_RESTART_COUNT", "0")
        return f"slurm-{environ['SLURM_JOB_ID']}.{step}.{restart}"
    return None


def current_rank(environ=None) -> Rank:
    """This process's rank, world size and launch id, from the launcher's environment variables."""
    environ = os.environ if environ is None else environ
    index = _int(environ, "RANK")
    world = _int(environ, "WORLD_SIZE")
    described = None
    if index is None and _int(environ, "SLURM_PROCID") is not None:
        index, world = _int(environ, "SLURM_PROCID"), _int(environ, "SLURM_NTASKS")
    if index is None:
        node, local = _int(environ, "NODE_RANK") or 0, _int(environ, "LOCAL_RANK") or 0
        # Lightning's launcher does not say how many processes a node has: only 0 vs not 0 is known.
        index = 0 if node == local == 0 else max(local, 1)
        described = f"local rank {local} of node {node}"
    world = max(world or 1, index + 1)
    if described is None:
        described = f"rank {index} of {world}"
    # A pipeline alone needs no shared id: it gets a fresh one if it starts ranks (Lightning's launcher).
    launch_id = _launcher_launch_id(environ) if world > 1 or environ.get(LAUNCH_ID_VARIABLE) else None
    return Rank(index, world, launch_id, described)


def _safe_name(launch_id: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in launch_id)


class LaunchFile:
    """Rank 0's side: what it plans, computes and why it stopped, in the launch file (see module doc).

    Written only where another rank may read it: from the start when the launch has several ranks, else
    from the first ``every_rank`` stage rank 0 computes (that stage may start the other ranks itself).
    Removed when the pipeline succeeds; kept with the error when it fails."""

    def __init__(self, cache_root: Path, rank: Rank):
        self.rank = rank
        self.launch_id = rank.launch_id or f"local-{os.getpid()}-{secrets.token_hex(6)}"
        self.path = cache_root / LAUNCHES_DIR / f"{_safe_name(self.launch_id)}.json"
        self.state: dict = {"plan": {}, "computing": {}, "error": None}
        self.written = False

    def _write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{secrets.token_hex(4)}")
        tmp.write_text(json.dumps(self.state, indent=1, sort_keys=True))
        os.replace(tmp, self.path)
        self.written = True

    def start(self, plan: dict[str, str], sized: dict | None = None) -> None:
        """The plan's keys and the values sized to rank 0's host (pipeline.sizing), which the other ranks apply."""
        self.state["plan"] = dict(plan)
        self.state["sized"] = dict(sized or {})
        self._remove_stale()
        if self.rank.world_size > 1:
            self._write()

    def computing(self, stage: str, key: str, resumed: bool, work_dir: Path) -> None:
        self.state["computing"][stage] = {"key": key, "resumed": resumed, "work_dir": str(work_dir)}
        self._write()

    def failed(self, exc: BaseException) -> None:
        if self.written or self.rank.world_size > 1:  # even before the plan: the other ranks wait for it
            self.state["error"] = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            with contextlib.suppress(OSError):
                self._write()

    def finished(self) -> None:
        if self.written:
            with contextlib.suppress(OSError):
                self.path.unlink()

    def _remove_stale(self) -> None:
        folder = self.path.parent
        if not folder.is_dir():
            return
        cutoff = time.time() - STALE_LAUNCH_SECONDS
        for old in folder.iterdir():
            with contextlib.suppress(OSError):
                if old.stat().st_mtime < cutoff:
                    old.unlink()


def read_launch_file(cache_root: Path, launch_id: str) -> dict | None:
    path = cache_root / LAUNCHES_DIR / f"{_safe_name(launch_id)}.json"
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError):  # absent, or (on a network filesystem) not complete yet
        return None
    return state if isinstance(state, dict) else None
