"""Cache keys (docs/design.md §8): sha256 over the stage name, its code version, the resolved config subtree it
declares, its inputs' keys and the fingerprint of its watched paths. Nothing else.

A stage may also declare ``resolve: module:function``, called at plan time as ``function(cfg, context)`` (``cfg``
the whole config, read-only; ``context`` a ``PlanContext``). It returns None (nothing to add: the key is exactly
as without the hook) or a mapping with any of
- ``config``: {top-level name: plain value}, added to the stage's config: the key covers it, the stage reads it;
- ``files``: {name: path}, files added to the stage's inputs under ``name``: the key covers their content
  (sha256), not their path, and the engine checks that content again before the stage runs;
- ``tags``: {name: text}, written on the stage's MLflow child run and on the parent run (lineage; not in the key).
What the hook raises is reported at plan time, naming the stage, before any stage runs.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from pipeline.cache import file_sha256
from pipeline.codeversion import code_version
from pipeline.dag import StageSpec, load_hook
from pipeline.errors import PipelineError
from pipeline.watch import watch_fingerprint

# The top-level packages whose modules, when a stage imports them (transitively), are part of its code version
# (besides its own top-level package): ``pipeline.code_packages`` in the config, else the engine alone.
DEFAULT_CODE_PACKAGES = ("pipeline",)


def code_packages(cfg: DictConfig) -> frozenset[str]:
    """``pipeline.code_packages``: a list of top-level package names (the engine's own is always among them)."""
    value = OmegaConf.select(cfg, "pipeline.code_packages", default=None)
    if value is None:
        return frozenset(DEFAULT_CODE_PACKAGES)
    value = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    if not isinstance(value, list) or not all(isinstance(v, str) and v.isidentifier() for v in value):
        raise PipelineError(f"pipeline.code_packages: expected a list of top-level package names, got {value!r}")
    return frozenset(value) | set(DEFAULT_CODE_PACKAGES)


def canonical_json(value) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=True)


def resolved_subtree(cfg: DictConfig, keys: tuple[str, ...]) -> dict:
    """{key: plain resolved value} for exactly the declared top-level keys."""
    out = {}
    for key in keys:
        value = cfg[key]
        out[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    return out


@dataclass(frozen=True)
class KeyParts:
    """Everything that goes into one stage's key, kept whole so that a miss can be explained."""

    stage: str
    code: dict[str, str]  # display path -> sha256 of every source file
    code_digest: str
    config: dict
    inputs: dict[str, str]  # input stage -> its key
    watch: dict[str, str]  # watched path -> digest
    # from the stage's ``resolve`` hook, outside the key: the files' paths (their digests are in ``inputs``) and tags
    files: dict[str, str] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)

    @property
    def key(self) -> str:
        payload = {
            "stage": self.stage,
            "code": self.code_digest,
            "config": self.config,
            "inputs": self.inputs,
            "watch": self.watch,
        }
        return hashlib.sha256(canonical_json(payload).encode()).hexdigest()

    def to_json(self) -> dict:
        return {
            "key": self.key,
            "stage": self.stage,
            "code_digest": self.code_digest,
            "code": self.code,
            "config": self.config,
            "inputs": self.inputs,
            "watch": self.watch,
        }


@dataclass(frozen=True)
class PlanContext:
    """What a ``resolve`` hook may need besides the config: where the cache and the tracking store are."""

    cache_dir: Path  # absolute
    tracking_uri: str


def default_context(cfg: DictConfig) -> PlanContext:
    """The context of a run from the current directory (the engine passes its own)."""
    cache_dir = Path(str(OmegaConf.select(cfg, "pipeline.cache_dir", default=".deepword_cache"))).expanduser()
    return PlanContext(cache_dir.absolute(), str(OmegaConf.select(cfg, "tracking.uri", default="")))


def file_digest(path: str | Path) -> str:
    return "sha256:" + file_sha256(Path(path))


@dataclass(frozen=True)
class Resolved:
    config: dict = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)


def resolve_extras(spec: StageSpec, cfg: DictConfig, context: PlanContext | None) -> Resolved:
    """Call the stage's ``resolve`` hook (see the module docstring) and check what it returned."""
    if spec.resolve is None:
        return Resolved()
    where = f"pipeline.stages.{spec.name}.resolve"
    func = load_hook(spec.name, "resolve", spec.resolve)
    try:
        out = func(cfg, context or default_context(cfg))
    except PipelineError:
        raise
    except Exception as exc:  # the hook's own message: what is wrong with the configuration, found at plan time
        raise PipelineError(f"stage '{spec.name}': {exc}") from exc
    if out is None:
        return Resolved()
    unknown = sorted(set(out) - {"config", "files", "tags"})
    if unknown:
        raise PipelineError(f"{where}: returned unknown field(s) {unknown}; allowed: config, files, tags")
    config = dict(out.get("config") or {})
    clash = [k for k in config if k in spec.config]
    if clash:
        raise PipelineError(f"{where}: returned config {clash} that the stage already declares")
    files = {str(k): str(v) for k, v in (out.get("files") or {}).items()}
    clash = [k for k in files if k in spec.inputs]
    if clash:
        raise PipelineError(f"{where}: returned file(s) named like the stage's inputs: {clash}")
    missing = [f"{k}={v}" for k, v in files.items() if not Path(v).is_file()]
    if missing:
        raise PipelineError(f"stage '{spec.name}': file(s) to start from not found: {missing}")
    return Resolved(config, files, {str(k): str(v) for k, v in (out.get("tags") or {}).items()})


def key_parts(spec: StageSpec, cfg: DictConfig, input_keys: dict[str, str],
              context: PlanContext | None = None) -> KeyParts:
    version = code_version(spec.module, code_packages(cfg))
    extra = resolve_extras(spec, cfg, context)
    return KeyParts(
        stage=spec.name,
        code=version.files,
        code_digest=version.digest,
        config={**resolved_subtree(cfg, spec.config), **extra.config},
        # an optional input left out of the run is absent from the key: the stage ran without it
        inputs={**{name: input_keys[name] for name in spec.inputs if name in input_keys or name not in spec.optional},
                **{name: file_digest(path) for name, path in extra.files.items()}},
        watch=watch_fingerprint(list(spec.watch)),
        files=extra.files,
        tags=extra.tags,
    )
