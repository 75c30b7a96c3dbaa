"""The command line: ``python -m pipeline`` / ``deepword`` with Hydra overrides, e.g.
``deepword profile=smoke pipeline.until=data``. Thin: composes the config and calls ``run_pipeline``.
"""

from __future__ import annotations

import signal
import sys
import traceback
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
    except Exception as exc:
        stage = getattr(exc, "pipeline_stage", None)
        if stage is None:
            raise  # not from a stage: an engine bug, keep Hydra's traceback
        # A stage's error (bad data, diverged training, a bug) as one line naming the stage; the
        # traceback goes to a file instead of burying the message.
        log = _traceback_file(exc)
        print(f"error: stage '{stage}' failed: {type(exc).__name__}: {exc}\n(traceback: {log})",
              file=sys.stderr, flush=True)
        sys.exit(1)


def _traceback_file(exc: BaseException) -> Path | str:
    from hydra.core.hydra_config import HydraConfig

    text = "".join(traceback.format_exception(exc))
    path = Path(HydraConfig.get().runtime.output_dir) / "error.log"
    try:
        path.write_text(text)
    except OSError:
        print(text, file=sys.stderr)
        return "printed above: the run directory is not writable"
    return path


def _exit_on_sigterm(signum, _frame) -> None:
    # Turn `kill` into an exception so a running stage's MLflow run is marked FAILED; its work dir is
    # kept (as after SIGKILL, which cannot be caught) so that the next run resumes from it.
    raise SystemExit(128 + signum)


def main() -> None:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    # MLflow takes seconds to import: let the tracking worker do it while Hydra composes.
    if not any(a in ("--help", "-h", "--cfg", "-c", "--info", "--hydra-help") for a in sys.argv[1:]):
        prestart_worker()
    _app()
