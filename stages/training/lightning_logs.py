"""Lightning's log lines printed once under the pipeline's logging.

``import lightning`` gives the ``lightning`` logger a console handler of its own, yet the logger still
propagates to the root logger, which Hydra configures (console and the job's log file): every Lightning
line ("GPU available", "`Trainer.fit` stopped") came out twice, once without the pipeline's format. (Its
``lightning.pytorch`` / ``lightning.fabric`` loggers, when imported before the root had handlers, print
through handlers of their own and do not propagate: their lines never reached the job's log file.)

Lightning's advertisement for its cloud logger (a "Tip" line at every ``Trainer``) is dropped: MLflow tracks the runs.

And Lightning's progress bar where it suits: on a terminal its own bar, elsewhere one line per epoch
(``lightning_progress``)."""

from __future__ import annotations

import logging
import sys
import time

from lightning.pytorch.callbacks import ProgressBar

from deepword.progress import on_terminal

ADVERTISEMENT = "\N{ELECTRIC LIGHT BULB} Tip:"


def _not_an_advertisement(record: logging.LogRecord) -> bool:
    """A logging filter: Lightning's "Tip" lines advertise a cloud service rather than say anything about the run."""
    return not str(record.msg).startswith(ADVERTISEMENT)


def route_lightning_logs() -> None:
    """When the root logger has handlers, drop the ``lightning`` logger's own, so its lines reach the
    console once, through the root's handlers. Without root handlers (a bare script) Lightning keeps its own.
    Either way its "Tip" advertisement is filtered out."""
    import lightning  # noqa: F401  (importing it is what adds the handler)

    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")  # where rank_zero_info logs
    rank_zero.addFilter(_not_an_advertisement)  # a filter already there is not added twice
    if not logging.getLogger().handlers:
        return
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            logger.removeHandler(handler)
        logger.propagate = True


def lightning_progress(name: str, stream=None) -> list:
    """Callbacks for ``Trainer(callbacks=...)``: none on a terminal (Lightning's own bar), else ``EpochLines``."""
    return [] if on_terminal(stream) else [EpochLines(name, stream)]


class EpochLines(ProgressBar):
    """Lightning's progress bar slot filled with one line per training epoch: ``name``, the epoch, its logged
    metrics, its time and an estimate of the time left (the mean wall time of this process's epochs so far,
    validation included, times the epochs to go): on a slower host than the profile's budget assumed (no
    native bf16, a busy machine) the first lines say how long the stage will take. A module-level class: DDP
    spawn pickles the Trainer's callbacks."""

    def __init__(self, name: str, stream=None):
        super().__init__()
        self.name, self.stream = name, stream
        self._enabled, self._started = True, 0.0
        self._fit_started, self._first_epoch = None, 0

    def disable(self) -> None:
        self._enabled = False

    def enable(self) -> None:
        self._enabled = True

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._started = time.perf_counter()
        if self._fit_started is None:  # the first epoch this process runs (a resumed fit starts later)
            self._fit_started, self._first_epoch = self._started, trainer.current_epoch

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        if not self._enabled or not trainer.is_global_zero:
            return
        metrics = " ".join(f"{k}={float(v):.4g}" for k, v in sorted(trainer.callback_metrics.items())
                           if getattr(v, "numel", lambda: 1)() == 1)
        now = time.perf_counter()
        done = trainer.current_epoch + 1
        timing = f"{now - self._started:.0f} s"
        to_go = (trainer.max_epochs or 0) - done
        if to_go > 0:
            per_epoch = (now - self._fit_started) / (done - self._first_epoch)
            timing += f", ~{format_duration(per_epoch * to_go)} left"
        print(f"{self.name} epoch {done}/{trainer.max_epochs}: {metrics} ({timing})",
              file=self.stream or sys.stderr, flush=True)


def format_duration(seconds: float) -> str:
    """``42 s``, ``7 min``, ``1 h 05 min``: as precise as an estimate of the time left deserves."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"
