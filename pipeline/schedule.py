"""Which stages to run side by side: the stages that will run, grouped into waves.

A stage may declare ``threads: <config key>``, the key that holds how many CPU threads it computes on (e.g.
``relation.train.threads``). Stages that declare one and whose inputs are ready run side by side, as long as their
threads add up to at most ``pipeline.cores``; every other stage runs alone, on the whole host. Two small networks
each trained on one thread side by side finish sooner than one after the other on two threads each: neither
fills two cores (on a 2-core host with bf16 the relation and facing stages take 458-494 s side by side against
~690 s one after the other, docs/engine.md). A stage that fills the host (the detector, near the host's peak
matrix-product rate) gains nothing from it, and a thread more than there are cores costs it many times over.

A wave holds at most one stage that must run in the engine's own process (``every_rank``).

The waves depend only on the plan and the configured thread counts, never on timing: the same config runs the same
stages together, and every stage computes from the same inputs and settings whichever runs beside it.
"""

from __future__ import annotations

import os

from omegaconf import DictConfig, OmegaConf

from pipeline.errors import PipelineError


def host_cores() -> int:
    """The CPUs this process may run on (its affinity, which a container or ``taskset`` narrows)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def cores(cfg: DictConfig) -> int:
    """``pipeline.cores`` (null: the host's, ``host_cores``): the cores side-by-side stages may fill together."""
    value = OmegaConf.select(cfg, "pipeline.cores", default=None)
    if value is None:
        return host_cores()
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise PipelineError(f"pipeline.cores: expected an integer >= 1 or null (the host's cores), got {value!r}")
    return value


def stage_threads(name: str, key: str | None, cfg: DictConfig) -> int | None:
    """The threads a stage declares through its ``threads`` key (None: it declares none and runs alone)."""
    if key is None:
        return None
    value = OmegaConf.select(cfg, key, default=None)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise PipelineError(f"pipeline.stages.{name}.threads: config key '{key}' should hold an integer >= 1 "
                            f"(the stage's CPU threads), got {value!r}")
    return value


def waves(order: list[str], inputs: dict[str, tuple[str, ...]], threads: dict[str, int | None],
          available: int, in_process: set[str] = frozenset()) -> list[list[str]]:
    """``order`` (the stages to compute, in dependency order) grouped into waves run one after the other.

    A wave starts with the first stage whose inputs are done (a stage not in ``order`` counts as done: a cache
    hit or left out) and takes, in order, every other ready stage that declares threads while the wave's threads
    stay within ``available``. A stage that declares none, or declares more than ``available``, runs alone. A wave
    holds at most one of the ``in_process`` stages: those run in the engine's own process (``every_rank`` stages,
    whose other ranks follow that process stage by stage).
    """
    done: set[str] = set()
    remaining = list(order)
    out: list[list[str]] = []
    while remaining:
        ready = [n for n in remaining if all(i in done or i not in order for i in inputs[n])]
        if not ready:  # cannot happen for a topological order; guard against a caller's mistake
            raise PipelineError(f"pipeline: stages {remaining} wait on each other")
        wave, used = [ready[0]], threads[ready[0]]
        if used is not None and used < available:
            for name in ready[1:]:
                t = threads[name]
                if t is not None and used + t <= available \
                        and not (name in in_process and any(w in in_process for w in wave)):
                    wave.append(name)
                    used += t
        out.append(wave)
        done.update(wave)
        remaining = [n for n in remaining if n not in wave]
    return out
