"""Cache keys (docs/design.md §8): sha256 over the stage name, its code version, the resolved config subtree it
declares, its inputs' keys and the fingerprint of its watched paths. Nothing else.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from pipeline.codeversion import code_version
from pipeline.dag import StageSpec
from pipeline.watch import watch_fingerprint

# Project modules a stage may import, whose changes invalidate it (besides its own top-level package).
PROJECT_PACKAGES = frozenset({"stages", "pipeline"})


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


def key_parts(spec: StageSpec, cfg: DictConfig, input_keys: dict[str, str]) -> KeyParts:
    version = code_version(spec.module, PROJECT_PACKAGES)
    return KeyParts(
        stage=spec.name,
        code=version.files,
        code_digest=version.digest,
        config=resolved_subtree(cfg, spec.config),
        # an optional input left out of the run is absent from the key: the stage ran without it
        inputs={name: input_keys[name] for name in spec.inputs if name in input_keys or name not in spec.optional},
        watch=watch_fingerprint(list(spec.watch)),
    )
