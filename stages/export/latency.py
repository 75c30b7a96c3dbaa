"""Latency as in the paper's Tables 1-2: the median wall time of a model call over many runs after a
warm-up, with the thread count fixed, onnxruntime and PyTorch eager measured on the same inputs in the
same process (so their ratio is meaningful even on a busy machine, where absolute times are not).

``cpu_ms``: on a shared machine wall time mostly measures the other processes, so onnxruntime is also
timed with one intra-op thread, which computes in the calling thread, by that thread's CPU time: close
to the wall time on an idle core (a two-thread run ideally takes half of it)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from deepword.inference.runtime import pad_graphs


def median_ms(call: Callable[[int], object], runs: int, warmup: int,
              clock: Callable[[], float] = time.perf_counter) -> float:
    """Median milliseconds of ``call(i)`` for i in range(runs), after ``warmup`` untimed calls."""
    if runs < 1:
        raise ValueError(f"export.latency.runs must be >= 1, got {runs}")
    for i in range(warmup):
        call(i)
    times = []
    for i in range(runs):
        start = clock()
        call(i)
        times.append(clock() - start)
    return 1000.0 * float(np.median(times))


def batches(feeds: Sequence[dict[str, np.ndarray]], batch: int) -> list[dict[str, np.ndarray]]:
    """Per-image feeds (each with batch dimension 1) -> feeds of ``batch`` consecutive images (cycling)."""
    out = []
    for start in range(0, len(feeds), batch):
        chosen = [feeds[(start + j) % len(feeds)] for j in range(batch)]
        out.append({k: np.concatenate([f[k] for f in chosen]) for k in chosen[0]})
    return out


def graph_batches(graphs: Sequence, size: int, batch: int, n: int | None = None) -> list[dict[str, np.ndarray]]:
    """Feeds of ``batch`` consecutive graphs each (cycling to fill the last), padded to ``n`` objects or,
    by default, to the largest graph of each batch (how the dynamic model runs a batch of images)."""

    groups = [[graphs[(start + j) % len(graphs)] for j in range(batch)] for start in range(0, len(graphs), batch)]
    return [pad_graphs(group, size, n)[0] for group in groups]


def onnx_ms(session, feeds: Sequence[dict[str, np.ndarray]], runs: int, warmup: int) -> float:
    """Median ms of one session call, cycling through ``feeds``."""
    return median_ms(lambda i: session.run(None, feeds[i % len(feeds)]), runs, warmup)


def cpu_ms(session, feeds: Sequence[dict[str, np.ndarray]], runs: int, warmup: int) -> float:
    """Median CPU milliseconds of one call of a one-thread session (see the module docstring)."""
    return median_ms(lambda i: session.run(None, feeds[i % len(feeds)]), runs, warmup, clock=time.thread_time)


def torch_ms(module, feeds: Sequence[dict[str, np.ndarray]], runs: int, warmup: int, threads: int) -> float:
    """Median ms of one eager forward pass of ``module`` with ``threads`` intra-op threads."""
    import torch

    tensors = [[torch.from_numpy(v) for v in f.values()] for f in feeds]
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.inference_mode():
            return median_ms(lambda i: module(*tensors[i % len(tensors)]), runs, warmup)
    finally:
        torch.set_num_threads(before)
