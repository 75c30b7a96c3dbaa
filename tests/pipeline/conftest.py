"""A toy project written to tmp_path for each test: three tiny stages in a uniquely named package
(``alpha`` -> ``beta``, plus an independent ``gamma``), a tmp cache and a tmp sqlite MLflow store.

The stages are controlled by their config: ``alpha.fail`` raises after writing a file, ``alpha.sleep``
waits (to be killed or to overlap) unless ``<counter>.nosleep`` exists, ``alpha.counter`` appends a line per computation (to count them
across processes).
"""

from __future__ import annotations

import shutil
import sys
import textwrap
import uuid
from dataclasses import dataclass
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from pipeline.codeversion import clear_memo

COMMON = "def scale(x):\n    return 2 * x\n"

ALPHA = """
import time
from pathlib import Path

from ..common import scale
from pipeline.tracking import stage_run_info


def run(cfg, inputs, out_dir):
    (out_dir / "value.txt").write_text(str(scale(cfg.alpha.value)))
    (out_dir / "artifacts").mkdir(exist_ok=True)  # a resumed attempt finds it there
    (out_dir / "artifacts" / "report.md").write_text("# alpha report")
    info = stage_run_info()
    (out_dir / "run_info.txt").write_text(repr(info))
    if cfg.alpha.counter:
        with open(cfg.alpha.counter, "a") as f:
            f.write("computed\\n")
    if cfg.alpha.sleep and not Path(cfg.alpha.counter + ".nosleep").exists():
        Path(cfg.alpha.counter + ".started").write_text("x")
        time.sleep(cfg.alpha.sleep)
    if cfg.alpha.fail:
        raise RuntimeError("alpha failed on purpose")
    return {"alpha.value": float(scale(cfg.alpha.value)), "alpha.seed": cfg.seed}
"""

BETA = """
def run(cfg, inputs, out_dir):
    value = int((inputs["a"] / "value.txt").read_text())
    (out_dir / "sum.txt").write_text(str(value + cfg.beta.offset))
    return {"beta.sum": float(value + cfg.beta.offset)}
"""

GAMMA = """
def run(cfg, inputs, out_dir):
    (out_dir / "g.txt").write_text("g")
    return {"gamma.ok": 1.0, "gamma.inputs": float(len(inputs))}
"""


@dataclass
class ToyProject:
    root: Path
    package: str
    db_uri: str

    def file(self, rel: str) -> Path:
        return self.root / self.package / rel

    def edit(self, rel: str, text: str) -> None:
        self.file(rel).write_text(text)
        clear_memo()

    def config(self, **dotted):
        cfg = OmegaConf.create(
            {
                "seed": 7,
                "profile_name": "toy",
                "alpha": {"value": 3, "fail": False, "sleep": 0, "counter": ""},
                "beta": {"offset": 10},
                "gamma": {"x": 1},
                "unrelated": {"knob": 1},
                "data": {"root": str(self.root / "dataset")},
                "tracking": {"uri": self.db_uri, "experiment": "toy", "require_server": False},
                "pipeline": {
                    "cache_dir": "cache",
                    "force": [],
                    "until": None,
                    "verify": "fast",
                    "stages": {
                        "a": {
                            "run": f"{self.package}.alpha.stage:run",
                            "inputs": [],
                            "config": ["alpha", "seed"],
                            "watch": ["${data.root}"],
                        },
                        "b": {"run": f"{self.package}.beta.stage:run", "inputs": ["a"], "config": ["beta"]},
                        "c": {"run": f"{self.package}.gamma.stage:run", "inputs": [], "config": ["gamma"]},
                    },
                },
            }
        )
        for key, value in dotted.items():
            OmegaConf.update(cfg, key.replace("__", "."), value, force_add=True)
        return cfg


def write_toy_project(root: Path, package: str) -> None:
    pkg = root / package
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "common.py").write_text(COMMON)
    (pkg / "unused.py").write_text("X = 1\n")
    for name, source in (("alpha", ALPHA), ("beta", BETA), ("gamma", GAMMA)):
        (pkg / name).mkdir()
        (pkg / name / "__init__.py").write_text("")
        (pkg / name / "stage.py").write_text(textwrap.dedent(source))
    (root / "dataset").mkdir()
    (root / "dataset" / "labels.jsonl").write_text('{"image": "a.png"}\n')


@pytest.fixture
def toy(tmp_path, monkeypatch, mlflow_template) -> ToyProject:
    package = f"toyproj_{uuid.uuid4().hex[:10]}"
    write_toy_project(tmp_path, package)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)  # relative cache_dir and MLflow's default artifact root land here
    clear_memo()
    shutil.copy(mlflow_template, tmp_path / "mlflow.db")
    yield ToyProject(tmp_path, package, f"sqlite:///{tmp_path}/mlflow.db")
    for name in [m for m in sys.modules if m.startswith(package)]:
        del sys.modules[name]
