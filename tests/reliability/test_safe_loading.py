"""Checkpoints and weights load with ``weights_only=True`` (docs/design.md §10): a file that would run code when
unpickled is refused by every loader, and no code path loads pickles another way."""

from __future__ import annotations

import ast
import json
import pathlib
import pickle
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


class _Exploit:
    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def _relation_dir(tmp_path: Path) -> Path:
    from stages.relation.model import ModelConfig

    (tmp_path / "relation.json").write_text(json.dumps({"model": ModelConfig().__dict__}))
    return tmp_path


def _detector_dir(tmp_path: Path) -> Path:
    from omegaconf import OmegaConf

    from stages.detector.model import model_config
    from tests.reliability.harness import compose_cfg

    cfg = compose_cfg(tmp_path, tmp_path / "cache", "sqlite:///unused.db")
    (tmp_path / "model.json").write_text(json.dumps(model_config(OmegaConf.to_container(cfg.detector, resolve=True))))
    return tmp_path


@pytest.mark.parametrize("loader, weights, make_dir", [
    ("stages.relation.stage:load_network", "relation.pt", _relation_dir),
    ("stages.detector.model:load_detector", "model.pt", _detector_dir),
])
def test_weights_file_that_would_run_code_is_refused(tmp_path, loader, weights, make_dir):
    import importlib

    module, func = loader.split(":")
    stage_dir = make_dir(tmp_path)
    marker = tmp_path / "code_ran"
    torch.save({"layer.weight": _Exploit(marker)}, stage_dir / weights)
    with pytest.raises(pickle.UnpicklingError, match="Weights only load failed"):
        getattr(importlib.import_module(module), func)(stage_dir)
    assert not marker.exists()


def _unsafe_loads(path: Path, root: Path = REPO) -> list[str]:
    """Calls that unpickle without ``weights_only=True``: torch.load, Trainer.fit(ckpt_path=...),
    load_from_checkpoint; and any pickle/joblib/dill load."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        owner = getattr(func.value, "id", "") if isinstance(func, ast.Attribute) else ""
        keywords = {k.arg: k.value for k in node.keywords}
        safe = isinstance(keywords.get("weights_only"), ast.Constant) and keywords["weights_only"].value is True
        needs_flag = (owner == "torch" and name == "load") or name == "load_from_checkpoint" \
            or (name == "fit" and "ckpt_path" in keywords)
        if (needs_flag and not safe) or (owner in ("pickle", "joblib", "dill", "cloudpickle") and name.startswith("load")):
            found.append(f"{path.relative_to(root)}:{node.lineno}")
    return found


def test_no_code_path_unpickles_without_weights_only():
    files = [p for d in ("stages", "pipeline", "benchmarks") for p in (REPO / d).rglob("*.py")]
    assert len(files) > 20
    assert [hit for f in files for hit in _unsafe_loads(f)] == []


def test_the_source_scan_flags_unsafe_loads(tmp_path):
    bad = tmp_path / "example.py"
    bad.write_text("import pickle, torch\nstate = torch.load('x.pt')\ntrainer.fit(m, ckpt_path='last.ckpt')\n"
                   "torch.load('y.pt', weights_only=False)\npickle.load(f)\ntorch.load('z.pt', weights_only=True)\n")
    assert _unsafe_loads(bad, tmp_path) == ["example.py:2", "example.py:3", "example.py:4", "example.py:5"]
