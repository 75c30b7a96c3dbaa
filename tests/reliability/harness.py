"""Running the real pipeline from reliability tests: in-process (``run_in_process``) or as a subprocess
(``pipeline_command``), on a tiny WORD dataset with training shrunk below the smoke profile."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

from tests.sqlite_store import fresh_store

REPO = Path(__file__).resolve().parents[2]

# Below the smoke profile: one torch thread, 28 px relation crops, 64 px detector input.
SHRINK = ["profile=smoke", "trainer.threads=1", "relation/backbone=conv_fc", "relation.model.hidden=32",
          "relation.model.embed_dim=16", "relation.model.gat_hidden=16", "detector.input_width=64",
          "detector.input_height=64", "detector.limit_train_batches=2", "detector.limit_val_batches=1"]


def overrides(data_root: Path, cache: Path, *extra: str) -> list[str]:
    return [*SHRINK, "data=word", f"data.root={data_root}", f"pipeline.cache_dir={cache}", *extra]


def compose_cfg(data_root: Path, cache: Path, tracking_uri: str, *extra: str):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config",
                       overrides=[*overrides(data_root, cache, *extra), f"tracking.uri={tracking_uri}"])


def run_in_process(data_root: Path, cache: Path, tracking_uri: str, *extra: str) -> dict:
    from pipeline.runner import run_pipeline

    cfg = compose_cfg(data_root, cache, tracking_uri, *extra)
    return run_pipeline(cfg, run_dir=cache.parent, in_process_tracking=True)


def pipeline_command(data_root: Path, cache: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "pipeline", *overrides(data_root, cache, *extra)]


def pipeline_env(tmp: Path) -> dict[str, str]:
    """The environment of a pipeline subprocess tracking to ``tmp/mlflow.db`` (created here from the
    initialised template unless it exists: the subprocess would spend seconds creating its tables)."""
    return {**os.environ, "MLFLOW_TRACKING_URI": fresh_store(Path(tmp) / "mlflow.db"), "DEEPWORD_THREADS": "1",
            "PYTHONUNBUFFERED": "1"}


def complete_entries(cache: Path, stage: str) -> list[Path]:
    """Entries under their final name (what a lookup could use); temp or partial work dirs excluded."""
    stage_dir = cache / stage
    if not stage_dir.is_dir():
        return []
    return sorted(p for p in stage_dir.iterdir() if not p.name.startswith(".") and (p / "manifest.json").exists())


def copy_upstream(upstream_cache: Path, cache: Path) -> None:
    """Put the data and priors entries of ``upstream_cache`` (conftest ``upstream``) and their latest-run
    records into ``cache``; mtimes are kept, so that the cache's fast verification accepts them."""
    for stage in ("data", "priors"):
        shutil.copytree(upstream_cache / stage, cache / stage, ignore=shutil.ignore_patterns(".locks", ".partial-*"))
