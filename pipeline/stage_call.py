"""Calling a stage's function, in this process or in one of its own beside other stages (``pipeline.schedule``).

The engine keeps everything else (locks, the cache's work dirs and commits, MLflow runs) in its own process: a
stage computed in a child process only runs its function there and sends back its metrics or its error. A stage
whose other ranks follow the engine's process (``every_rank``: Lightning's DDP launcher re-runs the engine's
command for them) runs in the engine's process, beside the others' processes.
"""

from __future__ import annotations

import copy
import multiprocessing as mp
import pickle
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import wait
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline import tracking
from pipeline.dag import StageSpec, load_hook
from pipeline.errors import PipelineError
from pipeline.keys import KeyParts


def check_metrics(stage: str, metrics) -> dict[str, float]:
    if metrics is None:
        return {}
    if not isinstance(metrics, dict):
        raise PipelineError(f"stage '{stage}' returned {type(metrics).__name__}, expected a dict of metrics")
    out = {}
    for k, v in metrics.items():
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise PipelineError(f"stage '{stage}': metric {k!r} is {v!r}, expected a number")
        out[str(k)] = float(v)
    return out


def stage_cfg(parts: KeyParts) -> DictConfig:
    """Only the declared keys (and what the stage's resolve hook added), resolved: exactly what the key hashes,
    read-only."""
    sub = OmegaConf.create(parts.config)
    OmegaConf.set_readonly(sub, True)
    OmegaConf.set_struct(sub, True)
    return sub


def call_stage(spec: StageSpec, parts: KeyParts, inputs, out_dir: Path, run: tuple[str, str]) -> dict[str, float]:
    """The stage's function on its config and inputs, writing into ``out_dir``; ``run`` is (tracking URI, MLflow
    run id) of its child run, which the stage may log to (``pipeline.tracking``)."""
    func = load_hook(spec.name, "run", f"{spec.module}:{spec.function}")
    tracking.set_active(run)
    try:
        return check_metrics(spec.name, func(stage_cfg(parts), inputs, out_dir))
    finally:
        tracking.set_active(None)


class StageProcessDied(PipelineError):
    """A stage's process ended without answering (killed, out of memory): like an interrupted stage, not a failed
    one, its work dir stays for the next attempt to resume from."""


@dataclass
class Job:
    """A stage to compute in a process of its own: what ``call_stage`` takes."""

    spec: StageSpec
    parts: KeyParts
    inputs: object  # pipeline.outputs.StageInputs
    out_dir: Path
    run: tuple[str, str]


@dataclass
class Outcome:
    """What a stage sent back: its metrics, or its error (re-raised by the engine) and, from a process of its own,
    the traceback it had there; ``seconds`` the stage took."""

    metrics: dict[str, float] | None
    error: BaseException | None
    traceback: str
    seconds: float


def _call(job: Job) -> Outcome:
    """The job's stage, here; its error caught into the outcome (an interrupt propagates)."""
    start = time.perf_counter()
    try:
        metrics = call_stage(job.spec, job.parts, job.inputs, job.out_dir, job.run)
    except Exception as exc:
        return Outcome(None, exc, "", time.perf_counter() - start)
    return Outcome(metrics, None, "", time.perf_counter() - start)


def _child(conn, job: Job) -> None:
    """A stage's process: its outcome, with the traceback it had here, sent back. An interrupt sends nothing: the
    engine sees the process end without an answer and keeps the work dir, as for an interrupted stage."""
    try:
        outcome = _call(job)
        if outcome.error is not None:
            outcome.traceback = "".join(traceback.format_exception(outcome.error))
            try:
                copy.copy(outcome.error)  # rebuilt from its arguments, as the engine's side of the pipe will
                pickle.dumps(outcome.error)
            except Exception:  # an exception that does not travel: its type and message do
                outcome.error = RuntimeError(f"{type(outcome.error).__name__}: {outcome.error}")
        conn.send(outcome)
    finally:
        conn.close()


def run_side_by_side(jobs: dict[str, Job], answered=None, here: str | None = None) -> dict[str, Outcome]:
    """Each job's stage at once: ``here`` (if given) in this process, every other one in a spawned process of its
    own. Waits for every one (a failure does not stop the others: what they compute is kept).
    ``answered(name, outcome, still_running)`` is called as each answers. An interrupt stops them all."""
    ctx = mp.get_context("spawn")  # a fresh interpreter: no torch threads or locks inherited from the engine
    start = time.perf_counter()
    procs, pending = {}, {}
    outcomes: dict[str, Outcome] = {}

    def answer(name: str, outcome: Outcome) -> None:
        outcomes[name] = outcome
        if answered is not None:
            answered(name, outcome, [n for n in jobs if n not in outcomes])

    try:
        for name, job in jobs.items():
            if name == here:
                continue
            receive, send = ctx.Pipe(duplex=False)
            proc = ctx.Process(target=_child, args=(send, job), name=f"stage-{name}")
            proc.start()
            send.close()
            procs[name], pending[receive] = proc, name
        if here is not None:
            answer(here, _call(jobs[here]))
        while pending:
            for receive in wait(list(pending)):
                name = pending.pop(receive)
                try:
                    answer(name, receive.recv())
                except EOFError:  # the process died without a word (killed, out of memory, interrupted)
                    procs[name].join()
                    error = StageProcessDied(f"stage '{name}': its process exited with code {procs[name].exitcode} "
                                             "before it answered; its work dir is kept for a re-run to resume from")
                    answer(name, Outcome(None, error, "", time.perf_counter() - start))
    except BaseException:  # the engine was interrupted (or failed): stop what still runs
        for proc in procs.values():
            if proc.is_alive():
                proc.terminate()
        raise
    finally:
        for proc in procs.values():
            proc.join()
    return outcomes
