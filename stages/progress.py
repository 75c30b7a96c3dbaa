"""Progress output that suits where it goes: a live bar on a terminal, plain lines in a log file or CI
(a bar redrawn with carriage returns becomes thousands of fragments on one line there).

``lightning_progress()`` gives a Trainer's progress callbacks; ``progress_lines`` wraps a loop."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator

LINE_FRACTION = 0.1  # a loop without a terminal prints a line every tenth of the way


def on_terminal(stream=None) -> bool:
    stream = sys.stderr if stream is None else stream
    return bool(getattr(stream, "isatty", lambda: False)())


def lightning_progress(name: str, stream=None) -> list:
    """Callbacks for ``Trainer(callbacks=...)``: none on a terminal (Lightning's own bar), else one line per
    epoch naming ``name``, the epoch, its logged metrics and its time."""
    if on_terminal(stream):
        return []
    return [_epoch_lines(name, stream)]


def _epoch_lines(name: str, stream=None):
    from lightning.pytorch.callbacks import ProgressBar

    class EpochLines(ProgressBar):
        """Lightning's progress bar slot filled with one line per training epoch."""

        def __init__(self):
            super().__init__()
            self._enabled, self._started = True, 0.0

        def disable(self) -> None:
            self._enabled = False

        def enable(self) -> None:
            self._enabled = True

        def on_train_epoch_start(self, trainer, pl_module) -> None:
            self._started = time.perf_counter()

        def on_train_epoch_end(self, trainer, pl_module) -> None:
            if not self._enabled or not trainer.is_global_zero:
                return
            metrics = " ".join(f"{k}={float(v):.4g}" for k, v in sorted(trainer.callback_metrics.items())
                               if getattr(v, "numel", lambda: 1)() == 1)
            print(f"{name} epoch {trainer.current_epoch + 1}/{trainer.max_epochs}: {metrics} "
                  f"({time.perf_counter() - self._started:.0f} s)", file=stream or sys.stderr, flush=True)

    return EpochLines()


def progress_lines(items: Iterable, total: int, desc: str, unit: str, stream=None) -> Iterator:
    """``items`` with progress: tqdm's bar on a terminal, else a line every ``LINE_FRACTION`` of ``total``."""
    if on_terminal(stream):
        from tqdm import tqdm

        yield from tqdm(items, total=total, desc=desc, unit=unit, file=stream)
        return
    out = stream or sys.stderr
    step = max(1, int(total * LINE_FRACTION))
    start = time.perf_counter()
    done = 0
    for item in items:
        yield item
        done += 1
        if done % step == 0 or done == total:
            print(f"{desc}: {done}/{total} {unit}s ({time.perf_counter() - start:.0f} s)", file=out, flush=True)
