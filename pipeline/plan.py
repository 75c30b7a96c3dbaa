"""The printed plan: each stage as HIT or MISS and why, explained against the stage's last key parts."""

from __future__ import annotations

import json
from dataclasses import dataclass

from pipeline.cache import Entry
from pipeline.keys import KeyParts

VALUE_CHARS = 60
CHANGES_SHOWN = 6   # a plan line names this many changed config leaves, then counts the rest (data=word against
                    # data=synword differs in ~90 leaves: all of them would bury the plan)
FILES_SHOWN = 8     # and this many changed source files (moving a package changes ~80)


@dataclass
class StagePlan:
    name: str
    parts: KeyParts
    hit: bool
    reason: str
    entry: Entry | None = None
    forced: bool = False

    @property
    def key(self) -> str:
        return self.parts.key


def _flatten(value, prefix: str = "") -> dict[str, object]:
    if isinstance(value, dict):
        out: dict[str, object] = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: value}


def _show(value) -> str:
    text = json.dumps(value) if value is not _ABSENT else "(absent)"
    return text if len(text) <= VALUE_CHARS else text[: VALUE_CHARS - 3] + "..."


_ABSENT = object()


def config_changes(old: dict, new: dict) -> list[str]:
    """``key: old -> new`` for every leaf that differs (added/removed leaves show ``(absent)``)."""
    a, b = _flatten(old), _flatten(new)
    return [
        f"{k}: {_show(a.get(k, _ABSENT))} -> {_show(b.get(k, _ABSENT))}"
        for k in sorted(set(a) | set(b))
        if a.get(k, _ABSENT) != b.get(k, _ABSENT)
    ]


def code_changes(old: dict, new: dict) -> list[str]:
    changed = [f for f in sorted(set(old) & set(new)) if old[f] != new[f]]
    added = [f"{f} (new)" for f in sorted(set(new) - set(old))]
    removed = [f"{f} (no longer used)" for f in sorted(set(old) - set(new))]
    return changed + added + removed


def explain_miss(parts: KeyParts, latest: dict | None, problem: str | None) -> str:
    """Why ``parts.key`` has no usable entry, in terms of what changed since the last run."""
    if problem:
        return f"entry corrupted ({problem}), recomputing"
    if latest is None:
        return "no entry yet"
    if latest.get("key") == parts.key:
        return "entry missing (removed, or its run was interrupted)"
    reasons = []
    if latest.get("code_digest") != parts.code_digest:
        files = code_changes(latest.get("code", {}), parts.code)
        more = f", ... and {len(files) - FILES_SHOWN} more" if len(files) > FILES_SHOWN else ""
        reasons.append("code changed: " + (", ".join(files[:FILES_SHOWN]) + more if files else "(file list unavailable)"))
    if latest.get("config") != parts.config:
        changes = config_changes(latest.get("config", {}), parts.config)
        more = f"; ... and {len(changes) - CHANGES_SHOWN} more" if len(changes) > CHANGES_SHOWN else ""
        reasons.append("config changed: " + "; ".join(changes[:CHANGES_SHOWN]) + more)
    old_inputs = latest.get("inputs", {})
    for name, key in parts.inputs.items():
        if old_inputs.get(name) != key:
            reasons.append(f"input {name} changed")
    if set(old_inputs) - set(parts.inputs):
        reasons.append(f"inputs changed: {sorted(old_inputs)} -> {sorted(parts.inputs)}")
    old_watch = latest.get("watch", {})
    changed_watch = [p for p in sorted(set(old_watch) | set(parts.watch)) if old_watch.get(p) != parts.watch.get(p)]
    if changed_watch:
        reasons.append("watched files changed: " + ", ".join(changed_watch))
    return "; ".join(reasons) if reasons else "key changed"


def explain_hit(parts: KeyParts, latest: dict | None) -> str:
    if latest is not None and latest.get("key") == parts.key:
        return "didn't change"
    return "cached entry from an earlier run"


def format_plan(plans: list[StagePlan], cache_root: str, left_out: dict[str, str]) -> str:
    width = max(len(p.name) for p in plans)
    lines = [f"Pipeline plan (cache: {cache_root}):"]
    for p in plans:
        lines.append(f"  {p.name:<{width}}  {'HIT ' if p.hit else 'MISS'}  {p.key[:10]}  {p.reason}")
    by_reason: dict[str, list[str]] = {}
    for name, why in left_out.items():
        by_reason.setdefault(why, []).append(name)
    lines += [f"  (not run, {why}: {', '.join(names)})" for why, names in by_reason.items()]
    return "\n".join(lines)
