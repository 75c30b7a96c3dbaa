"""Plan-time sizing: a stage's budget chosen to fit this host, then fixed, printed and recorded.

A stage may declare ``size: module:function``. Before the value checks and the cache keys, the engine calls
``function(cfg, context)`` (``cfg`` the whole config, read-only; ``context`` a ``pipeline.keys.PlanContext``) for each
selected stage that declares one. It returns None (nothing to size: the config gives its budget outright) or a
mapping ``{"config": {dotted key: value}, "note": str}``. The values replace the config's (each key lies under one of
the stage's declared config names), so the cache key, the stage, the MLflow params and every later hook see them as if
they had been given on the command line: the same config with those values given explicitly reproduces the run on any
host, under the same cache key. The plan prints each value with its note; the parent run logs it as the param
``sized.<key>`` beside the config's own.

A sizing is remembered per host and stage config in the cache (``.sizing.json``): a timing probe varies from run to
run, and a budget that moved with it would miss the cache each time. Another host (another name, processor or core
count) is probed again; deleting the file measures again here. One process sizes at a time (a lock in the temporary
directory). Ranks other than 0 take rank 0's values (its launch file).
"""

from __future__ import annotations

import contextlib
import copy
import fcntl
import hashlib
import json
import os
import platform
import tempfile
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from pipeline.cache import replace_text_best_effort
from pipeline.dag import StageSpec, load_hook
from pipeline.errors import PipelineError
from pipeline.keys import canonical_json, resolved_subtree

MEMO_FILE = ".sizing.json"


@dataclass(frozen=True)
class Sized:
    stage: str
    values: dict  # dotted config key -> value
    note: str
    remembered: bool  # from the memo, not probed in this run


def host_fingerprint() -> str:
    """What makes a host's timings its own: its name, architecture, processor model and cores."""
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        model = platform.processor()
    return f"{platform.node()}|{platform.machine()}|{model}|{os.cpu_count()}"


def _memo_key(spec: StageSpec, cfg: DictConfig) -> str:
    payload = {"stage": spec.name, "hook": spec.size, "config": resolved_subtree(cfg, spec.config),
               "host": host_fingerprint()}
    return hashlib.sha256(canonical_json(payload).encode()).hexdigest()


def _read_memo(path: Path) -> dict:
    try:
        memo = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return memo if isinstance(memo, dict) else {}


def _call(spec: StageSpec, cfg: DictConfig, context) -> dict | None:
    func = load_hook(spec.name, "size", spec.size)
    try:
        out = func(cfg, context)
    except PipelineError:
        raise
    except Exception as exc:  # the hook's own message: the stage cannot be sized as configured
        raise PipelineError(f"stage '{spec.name}': cannot size it to this host: {exc}") from exc
    if out is None:
        return None
    if not isinstance(out, dict) or set(out) - {"config", "note"} or not isinstance(out.get("config"), dict):
        raise PipelineError(f"pipeline.stages.{spec.name}.size: expected None or {{'config': {{key: value}}, "
                            f"'note': str}}, got {out!r}")
    outside = [k for k in out["config"] if str(k).split(".")[0] not in spec.config]
    if outside:
        raise PipelineError(f"pipeline.stages.{spec.name}.size: sized {outside}, outside the stage's config "
                            f"{list(spec.config)}")
    return {"config": {str(k): v for k, v in out["config"].items()}, "note": str(out.get("note") or "")}


def apply_sized(cfg: DictConfig, values: dict) -> DictConfig:
    """A copy of ``cfg`` with the sized values in place (the caller's config is left as it was)."""
    if not values:
        return cfg
    sized = copy.deepcopy(cfg)
    with open_dict(sized):
        for key, value in values.items():
            OmegaConf.update(sized, key, value, merge=False)
    return sized


def size_stages(specs: dict[str, StageSpec], selected: list[str], cfg: DictConfig, cache_root: Path,
                context) -> tuple[DictConfig, list[Sized]]:
    """Call the selected stages' ``size`` hooks (or take their remembered answers); returns the sized config and what
    was sized."""
    hooked = [specs[name] for name in selected if specs[name].size is not None]
    if not hooked:
        return cfg, []
    with _memo_lock(Path(cache_root)):
        return _size_locked(hooked, cfg, Path(cache_root), context)


@contextlib.contextmanager
def _memo_lock(cache_root: Path):
    """One process at a time reads, probes and writes the memo: the jobs of a parallel sweep would otherwise probe
    side by side, each under the others' load, and size one shared stage differently (two keys, two trainings). The
    lock lives in the temporary directory, not the cache: a run whose sizing fails must leave no cache behind. (Sizing
    is per host, and so is the lock.)"""
    digest = hashlib.sha256(str(cache_root.absolute()).encode()).hexdigest()[:16]
    path = Path(tempfile.gettempdir()) / f"pipeline-sizing-{digest}.lock"
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:  # no writable temporary directory: size without the lock
            yield
            return
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:  # the holder before us removes the file as it leaves: then ours is a stale inode, open the new one
            if os.fstat(fd).st_ino == os.stat(path).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):  # removed while held, so no lock file is left behind in the tempdir
            path.unlink()
        os.close(fd)  # closing releases the flock


def _size_locked(hooked: list[StageSpec], cfg: DictConfig, cache_root: Path, context) -> tuple[DictConfig, list[Sized]]:
    memo_path = cache_root / MEMO_FILE
    memo, changed, sized = _read_memo(memo_path), False, []
    for spec in hooked:
        key = _memo_key(spec, cfg)
        out, remembered = memo.get(key), True
        if out is None:
            out, remembered = _call(spec, cfg, context), False
            if out is None:  # nothing to size (e.g. the epochs are given): nothing to remember either
                continue
            memo[key], changed = out, True
        cfg = apply_sized(cfg, out["config"])
        sized.append(Sized(spec.name, dict(out["config"]), out.get("note", ""), remembered))
    if changed:
        replace_text_best_effort(memo_path, json.dumps(memo, indent=1, sort_keys=True))
    return cfg, sized


def sized_values(sized: list[Sized]) -> dict:
    """{dotted key: value} of every sizing, for the launch file (the other ranks apply the same)."""
    return {k: v for s in sized for k, v in s.values.items()}


def format_sized(sized: list[Sized], cache_root: Path) -> str:
    """The plan's lines: each sized value, how it was reached, and how to fix it."""
    if not sized:
        return ""
    lines = ["Sized to this host (give the value explicitly to reproduce the run elsewhere):"]
    for s in sized:
        values = " ".join(f"{k}={v}" for k, v in s.values.items())
        when = f" (remembered in {Path(cache_root) / MEMO_FILE}: delete it to measure again)" if s.remembered else ""
        lines.append(f"  {s.stage}: {values}: {s.note}{when}")
    return "\n".join(lines)


def sized_params(sized: list[Sized]) -> dict[str, str]:
    """The parent run's params: ``sized.<key>`` for each value sized to the host."""
    return {f"sized.{k}": str(v) for s in sized for k, v in s.values.items()}
