"""The command line: ``python -m pipeline`` / ``deepword run`` with Hydra overrides, e.g.
``deepword run profile=smoke pipeline.until=data`` (or ``python -m pipeline profile=smoke pipeline.until=data``). Thin: composes the config and calls ``run_pipeline``.
"""

from __future__ import annotations

import signal
import sys
import traceback
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.runmode import is_single_run
from pipeline.runner import run_pipeline

# ``../conf`` made absolute: a relative config_path in a package turns into a ``pkg://`` lookup that
# fails outside the repo root (the console script runs from anywhere).
CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")

CONF_NAME = "config"
INFO_FLAGS = ("--help", "-h", "--cfg", "-c", "--info", "--hydra-help", "--shell-completion", "-sc")


def spawnable_start_method() -> None:
    """Each job of a parallel sweep runs in a joblib (loky) worker, whose default multiprocessing start
    method is 'loky': a process spawned from the job restores its parent's default first and dies on
    it, so a stage's process pool (the synthetic data renderer) never started. Reset it to 'spawn'."""
    import multiprocessing as mp

    if mp.get_start_method(allow_none=True) not in (None, *mp.get_all_start_methods()):
        mp.set_start_method("spawn", force=True)


def _app(cfg) -> None:
    spawnable_start_method()
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
    if getattr(exc, "stage_traceback", ""):  # computed in a process of its own (pipeline.stage_call): where it failed
        text += "\nIn the stage's process:\n" + exc.stage_traceback
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


def _compose_once_if_single_run(argv: list[str]) -> None:
    """Skip Hydra's extra compose that only reads ``hydra.mode`` when no config or flag can set it
    (``pipeline.runmode``); any unusual command line keeps Hydra's own check."""
    from hydra._internal.hydra import Hydra
    from hydra._internal.utils import get_args_parser

    try:
        args, _ = get_args_parser().parse_known_args(argv)
    except SystemExit:
        return  # Hydra reports the bad command line itself
    if args.multirun or args.config_dir is not None:
        return
    conf_dir = Path(args.config_path or CONF_DIR)
    if not conf_dir.is_absolute():
        return
    if is_single_run(conf_dir, args.config_name or CONF_NAME, list(args.overrides)):
        # What Hydra's get_mode returns when nothing sets hydra.mode: a plain run.
        Hydra.get_mode = lambda self, config_name, overrides: None


def main() -> None:
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    argv = sys.argv[1:]
    if any(a in INFO_FLAGS for a in argv):
        return _hydra_app()()
    _compose_once_if_single_run(argv)
    _hydra_app()()


def _hydra_app():
    import hydra

    return hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=CONF_NAME)(_app)
