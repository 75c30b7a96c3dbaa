"""The command line: ``python -m pipeline`` / ``deepword`` with Hydra overrides, e.g.
``deepword profile=smoke pipeline.until=data``. Thin: composes the config and calls ``run_pipeline``.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from pipeline.errors import PipelineError
from pipeline.tracker import prestart_worker

# ``../conf`` made absolute: a relative config_path in a package turns into a ``pkg://`` lookup that
# fails outside the repo root (the console script runs from anywhere).
CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="config")
def _app(cfg: DictConfig) -> None:
    from pipeline.runner import run_pipeline

    try:
        run_pipeline(cfg)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        sys.exit(1)


def _exit_on_sigterm(signum, _frame) -> None:
    # Turn `kill` into an exception so a running stage's temp dir is removed and its MLflow run is
    # marked FAILED (SIGKILL cannot be caught; its leftovers are swept by the next run).
    raise SystemExit(128 + signum)


def main() -> None:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    # MLflow takes seconds to import: let the tracking worker do it while Hydra composes.
    if not any(a in ("--help", "-h", "--cfg", "-c", "--info", "--hydra-help") for a in sys.argv[1:]):
        prestart_worker()
    _app()
