"""Whether an invocation is certainly a single run, so Hydra need not compose the config twice.

Hydra composes the whole config once only to read ``hydra.mode`` (``Hydra.get_mode``) and then again
for the run: on a no-op re-run that first compose is a third of the engine's own time. The mode can
only come from ``--multirun``, a ``hydra.mode`` override or a config file that sets ``hydra.mode``; this
module finds those files with a text scan (a few ms) and says "single run" only when none of them is
selected, so anything unusual falls back to Hydra's own (composing) check.
"""

from __future__ import annotations

import re
from pathlib import Path

_MODE_LINE = re.compile(r"\bmode\s*:")
_DEFAULTS_ENTRY = re.compile(r"^\s*-\s*(?:override\s+)?/?(?:optional\s+)?([\w/]+)(?:@\S+)?\s*:\s*(\S*)")


def _sets_hydra_mode(path: Path) -> bool:
    text = path.read_text()
    if not _MODE_LINE.search(text):
        return False
    import yaml  # only for the few candidate files; imported after the tracking worker has started

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        return True  # unreadable here: let Hydra decide
    if not isinstance(data, dict):
        return True
    hydra = data.get("hydra")  # e.g. priors' own ``mode:`` key is not Hydra's
    return hydra is not None and (not isinstance(hydra, dict) or "mode" in hydra)


def _selected_groups(path: Path) -> dict[str, str]:
    """Defaults-list entries ``group: option`` of one config file (a text scan, conservative)."""
    return {m.group(1): m.group(2) for m in map(_DEFAULTS_ENTRY.match, path.read_text().splitlines()) if m}


def is_single_run(conf_dir: Path, config_name: str, overrides: list[str]) -> bool:
    """True when no ``--multirun``-like setting can be in effect for these overrides (see module doc)."""
    primary = conf_dir / f"{config_name}.yaml"
    if not primary.is_file():
        return False
    files = sorted(conf_dir.rglob("*.yaml"))
    mode_groups = set()
    for f in files:
        if _sets_hydra_mode(f):
            if f == primary:
                return False
            mode_groups.add(f.parent.relative_to(conf_dir).as_posix())
    for o in overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if key.startswith("hydra.mode") or key in mode_groups:
            return False
    for f in files:
        for group, option in _selected_groups(f).items():
            if group.lstrip("/") in mode_groups and not (f == primary and option == "null"):
                return False
    return True
