"""Progress output that suits where it goes: a live bar on a terminal, plain lines in a log file or CI
(a bar redrawn with carriage returns becomes thousands of fragments on one line there).

``progress_lines`` wraps a loop; ``ProgressCounter`` follows work reported as (done, total) by a callback;
``stages.training.lightning_logs.lightning_progress`` gives a Trainer's callbacks."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator

LINE_FRACTION = 0.1  # a loop without a terminal prints a line every tenth of the way


def on_terminal(stream=None) -> bool:
    stream = sys.stderr if stream is None else stream
    return bool(getattr(stream, "isatty", lambda: False)())


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


class ProgressCounter:
    """Progress reported by a callback, ``update(done, total)``, as ``progress_lines`` shows a loop: tqdm's bar on a
    terminal, else a line each time another ``LINE_FRACTION`` of ``total`` is done (and one at the end)."""

    def __init__(self, desc: str, unit: str, stream=None):
        self.desc, self.unit, self.stream = desc, unit, stream
        self.start = time.perf_counter()
        self.printed = 0   # the count of the last line printed
        self.bar = None
        if on_terminal(stream):
            from tqdm import tqdm

            self.bar = tqdm(desc=desc, unit=unit, file=stream, leave=False, mininterval=5.0)

    def __call__(self, done: int, total: int) -> None:
        self.update(done, total)

    def update(self, done: int, total: int) -> None:
        if self.bar is not None:
            self.bar.total, self.bar.n = total, done
            self.bar.refresh()
            return
        step = max(1, int(total * LINE_FRACTION))
        if done // step > self.printed // step or (done == total and self.printed != done):
            self.printed = done
            print(f"{self.desc}: {done}/{total} {self.unit}s ({time.perf_counter() - self.start:.0f} s)",
                  file=self.stream or sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
