"""Frames fitted in worker processes: the bev stage's footprints and ``deepword infer``'s.

Fitting a frame's footprints is plain NumPy on one core (a one-wheel or no-wheel vehicle's silhouette search projects
thousands of vehicles), and a frame's footprints depend on that frame alone. So the frames go to spawned processes in
tasks of a few, and the numbers are the same for any number of processes."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator, Sequence

# A spawned process costs 2-3 s before it fits anything (importing NumPy, OpenCV and the project), about what a few
# frames take (a smoke run's 3-4 test frames: 6 s in two processes, under 3 s in one): frames go to worker processes
# only where each gets at least this many, in tasks of this many
FRAMES_PER_TASK = 8


def frame_processes(workers: int, frames: int, frames_per_task: int | None = None) -> int:
    """How many processes ``map_frames`` fits ``frames`` frames in with ``workers`` allowed: no more than give each
    ``frames_per_task`` frames (``FRAMES_PER_TASK`` by default); 1 is the calling process."""
    return max(1, min(int(workers), frames // _per_task(frames_per_task)))


def _per_task(frames_per_task: int | None) -> int:
    return max(1, int(FRAMES_PER_TASK if frames_per_task is None else frames_per_task))


def map_frames(fit: Callable, frames: Sequence, workers: int = 1,
               progress: Callable[[Iterable, int], Iterator] | None = None,
               frames_per_task: int | None = None) -> list:
    """``[fit(frame) for frame in frames]``, in their order; with ``workers`` > 1 in up to that many spawned processes
    (``frame_processes``), ``frames_per_task`` frames a task (``FRAMES_PER_TASK`` by default). ``fit`` must pickle
    (a module-level function, or a ``functools.partial`` of one). ``progress(results, total)`` wraps the results as
    they arrive (e.g. ``deepword.progress.progress_lines``)."""
    processes = frame_processes(workers, len(frames), frames_per_task)
    if processes == 1:
        results = map(fit, frames)
        return list(results if progress is None else progress(results, len(frames)))
    # spawn, not fork: safe whatever threads the parent runs (torch's, onnxruntime's)
    with mp.get_context("spawn").Pool(processes) as pool:
        results = pool.imap(fit, frames, chunksize=_per_task(frames_per_task))
        return list(results if progress is None else progress(results, len(frames)))
