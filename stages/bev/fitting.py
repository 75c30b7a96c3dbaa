"""The bev stage's footprints: every (box source, method)'s fused footprints on the test frames
(``deepword.footprint.frame_footprints``, what ``deepword infer`` gives the same frame), the frames shared among
worker processes.

Fitting is the stage's cost (a one-wheel or no-wheel vehicle's silhouette search: thousands of projected vehicles
per fit) and plain NumPy on one core, so ``bev.workers`` processes each take every ``workers``-th frame and fit it
for every (box source, method) within one ``shared_fits`` (the methods of a box source share their boxes, and most
vehicles are fitted alike by several). A frame's footprints depend on that frame alone, so the numbers are the same
for any number of workers."""

from __future__ import annotations

import multiprocessing as mp
import time
from collections import defaultdict

from deepword.footprint import (
    FootprintPrior,
    facing_trust,
    frame_footprints,
    refuse_weighed,
    shared_fits,
)
from deepword.word_format import Record

# A spawned process costs 2-3 s before it fits anything (importing NumPy, OpenCV and the project), about what it
# takes to fit a few frames: fewer frames than this a process are fitted in the calling one (a smoke run's 3-4 test
# frames: 6 s in two processes, under 3 s in one).
MIN_FRAMES_PER_PROCESS = 8

# (box source, method) -> ({frame: [(record, camera), ...]}, use_relations)
Jobs = dict[tuple[str, str], tuple[dict[int, list], bool]]


def frame_views(preds: dict[str, Record], test: list[Record], cameras: dict) -> dict[int, list]:
    """{frame: [(predicted record, camera), ...]} of the test images a method predicted, in test order."""
    views = defaultdict(list)
    for rec in test:
        pred = preds.get(rec.image)
        if pred is not None:
            views[rec.frame_id].append((pred, cameras[rec.image]))
    return dict(views)


def facing_lead(boxes: str, methods: list[str]) -> tuple[str, str]:
    """The job whose footprints judge a box source's facing votes (their cameras' agreement, ``facing_trust``):
    DeepWORD's where it is among ``methods`` (the relation methods scored on those boxes), else the first."""
    return boxes, "deepword" if "deepword" in methods else methods[0]


def _fit_frames(jobs: Jobs, frames: list[int], prior: FootprintPrior, radius_m: float) -> dict:
    """{job: {frame: (its estimates, their fused footprints)}} for ``frames``, every job's fits shared
    (``shared_fits``)."""
    with shared_fits():
        return {key: {f: frame_footprints(views.get(f, []), prior, radius_m, use_relations) for f in frames}
                for key, (views, use_relations) in jobs.items()}


def fused_footprints(jobs: Jobs, frames: list[int], prior: FootprintPrior, radius_m: float,
                     workers: int = 1, min_frames_per_process: int = MIN_FRAMES_PER_PROCESS,
                     facing_val_accuracy: float | None = None
                     ) -> tuple[dict[tuple[str, str], dict[int, list]], dict[str, float]]:
    """{job: {frame: [(footprint, its estimates), ...]}} for every job and every frame of ``frames`` (a frame none
    of a job's views fall in gets none), keyed in the order of ``frames``, and {box source: the weight its facing votes
    were given}; ``workers`` > 1: up to that many spawned processes, each every ``workers``-th frame, as long as each
    gets ``min_frames_per_process`` frames. With ``facing_val_accuracy`` (the facing network's, 0-1) each box source's
    votes are weighed by ``facing_trust`` of its ``facing_lead`` job's footprints, and where that is under 1 its
    methods' frames are fused again with the weighed votes."""
    started = time.perf_counter()
    order = sorted(frames)
    workers = max(1, min(int(workers), len(order) // max(1, int(min_frames_per_process))))
    shards = [order[i::workers] for i in range(workers)]
    if workers == 1:
        parts = [_fit_frames(jobs, order, prior, radius_m)]
    else:
        args = [({key: ({f: views[f] for f in shard if f in views}, use) for key, (views, use) in jobs.items()},
                 shard, prior, radius_m) for shard in shards]
        with mp.get_context("spawn").Pool(workers) as pool:   # spawn: safe whatever threads the parent runs
            parts = pool.starmap(_fit_frames, args)
    out = {key: {f: part[key][f] for part in parts for f in part[key]} for key in jobs}
    trust = {}
    if facing_val_accuracy is not None:
        for boxes in dict.fromkeys(b for b, _ in jobs):
            voted = [key for key, (_, use) in jobs.items() if key[0] == boxes and use]
            if not voted:
                continue
            lead = facing_lead(boxes, [method for _, method in voted])
            trust[boxes] = facing_trust([g for _, fused in out[lead].values() for g in fused], facing_val_accuracy)
            for key in voted:
                out[key] = refuse_weighed(out[key], trust[boxes], radius_m, prior)
    print(f"bev: footprints of {len(order)} frames x {len(jobs)} (boxes, method) in "
          f"{time.perf_counter() - started:.0f} s ({workers} process{'es' if workers > 1 else ''})"
          + "".join(f"; {b} boxes' facing votes x {w:.2f}" for b, w in trust.items() if w < 1.0), flush=True)
    return {key: {f: fused[f][1] for f in frames} for key, fused in out.items()}, trust
