"""Plan-time time estimates: how long the stages that will run are expected to take on this host.

A stage may declare ``estimate: module:function``. For each stage the plan marks MISS (never for a hit: an all-hit
re-run stays as fast as before), the engine calls ``function(cfg, context)`` (``cfg`` the whole config, read-only;
``context`` a ``pipeline.keys.PlanContext``) before anything runs. It returns None (no estimate), a number of
seconds, or a mapping ``{"seconds": float, "note": str, "hint": str}`` (``note``: how the figure was reached,
printed beside it; ``hint``: what would shorten the stage, printed when the total is over budget). Estimates never
change a cache key or a result: they are printed, written to ``summary.json`` and logged as the parent run's params
``estimate.<stage>.seconds``. A hook that raises costs the run its estimate, not the run: the plan says why.

``pipeline.time_budget_minutes`` (null: no budget) makes the plan warn when the estimated total is over it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from pipeline.dag import StageSpec, load_hook
from pipeline.errors import PipelineError


@dataclass(frozen=True)
class Estimate:
    stage: str
    seconds: float | None  # None: the hook failed or gave no estimate (``note`` says why)
    note: str = ""
    hint: str = ""


def _check(stage: str, out) -> Estimate | None:
    if out is None:
        return None
    if isinstance(out, bool):
        raise PipelineError(f"stage '{stage}': estimate hook returned {out!r}, expected seconds or a mapping")
    if isinstance(out, int | float):
        out = {"seconds": out}
    if not isinstance(out, dict):
        raise PipelineError(f"stage '{stage}': estimate hook returned {type(out).__name__}, expected seconds or a mapping")
    unknown = sorted(set(out) - {"seconds", "note", "hint"})
    if unknown:
        raise PipelineError(f"stage '{stage}': estimate hook returned unknown field(s) {unknown}; "
                            "allowed: seconds, note, hint")
    seconds = out.get("seconds")
    if isinstance(seconds, bool) or not isinstance(seconds, int | float) or not math.isfinite(seconds) or seconds < 0:
        raise PipelineError(f"stage '{stage}': estimate hook returned seconds={seconds!r}, expected a number >= 0")
    return Estimate(stage, float(seconds), str(out.get("note") or ""), str(out.get("hint") or ""))


def estimate_stage(spec: StageSpec, cfg: DictConfig, context) -> Estimate | None:
    """Call the stage's ``estimate`` hook; a failure becomes an estimate without seconds that says why."""
    if spec.estimate is None:
        return None
    try:
        return _check(spec.name, load_hook(spec.name, "estimate", spec.estimate)(cfg, context))
    except Exception as exc:  # an estimate is advice: the run goes on without it
        return Estimate(spec.name, None, f"no estimate ({type(exc).__name__}: {exc})")


def time_budget(cfg: DictConfig) -> float | None:
    """``pipeline.time_budget_minutes`` in seconds, or None."""
    value = OmegaConf.select(cfg, "pipeline.time_budget_minutes", default=None)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
        raise PipelineError(f"pipeline.time_budget_minutes: expected a number > 0 or null, got {value!r}")
    return 60.0 * float(value)


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def format_estimates(estimates: list[Estimate], budget_seconds: float | None, profile: str = "",
                     together: list[list[str]] = ()) -> str:
    """The plan's estimate lines: one per stage with a hook, the total, and a warning when over budget.
    ``together``: the stages that run side by side (``pipeline.schedule``'s waves); a wave counts as its longest."""
    if not estimates:
        return ""
    width = max(len("total"), *(len(e.stage) for e in estimates))   # the total line aligns with the stages
    wave_of = {name: wave for wave in together for name in wave}
    lines = ["Estimated time of the stages to run, on this host:"]
    for e in estimates:
        figure = "?" if e.seconds is None else _duration(e.seconds)
        beside = [n for n in wave_of.get(e.stage, [e.stage]) if n != e.stage]
        note = e.note + (f"; beside {', '.join(beside)}" if beside else "")
        lines.append(f"  {e.stage:<{width}}  {figure:>9}  {note}".rstrip())
    known = [e for e in estimates if e.seconds is not None]
    if not known:
        return "\n".join(lines)
    longest: dict[tuple[str, ...], float] = {}  # a wave's time: its longest stage's
    for e in known:
        wave = tuple(wave_of.get(e.stage, [e.stage]))
        longest[wave] = max(longest.get(wave, 0.0), e.seconds)
    total = sum(longest.values())
    side = "; stages side by side count as the longest of them" if any(len(w) > 1 for w in longest) else ""
    lines.append(f"  {'total':<{width}}  {_duration(total):>9}  (stages without an estimate hook not counted{side})")
    if budget_seconds is not None and total > budget_seconds:
        slowest = max(known, key=lambda e: e.seconds)
        where = f" of profile {profile}" if profile else ""
        lines.append(f"WARNING: this host is slow for this configuration: ~{_duration(total)} for the stages to run, over the "
                     f"{_duration(budget_seconds)} budget{where} (pipeline.time_budget_minutes). The slowest is "
                     f"'{slowest.stage}' (~{_duration(slowest.seconds)})"
                     + (f": {slowest.hint}" if slowest.hint else "") + ".")
    return "\n".join(lines)


def estimate_params(estimates: list[Estimate]) -> dict[str, str]:
    """The parent run's params: ``estimate.<stage>.seconds`` for each stage estimated."""
    return {f"estimate.{e.stage}.seconds": f"{e.seconds:.1f}" for e in estimates if e.seconds is not None}
