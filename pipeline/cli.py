"""The command line: ``python -m pipeline`` / ``deepword`` with Hydra overrides, e.g.
``deepword profile=smoke pipeline.until=data``. Thin: composes the config and calls ``run_pipeline``.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from pipeline.errors import PipelineError
from pipeline.tracker import prestart_worker


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def _app(cfg: DictConfig) -> None:
    from pipeline.runner import run_pipeline

    try:
        run_pipeline(cfg)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        sys.exit(1)


def main() -> None:
    # MLflow takes seconds to import: let the tracking worker do it while Hydra composes.
    if not any(a in ("--help", "-h", "--cfg", "-c", "--info", "--hydra-help") for a in sys.argv[1:]):
        prestart_worker()
    _app()
