"""The bev stage's footprints: every (box source, method)'s fused footprints on the test frames
(``deepword.footprint.frame_footprints``, what ``deepword infer`` gives the same frame), the frames shared among
worker processes (``deepword.frame_processes``).

Each frame is fitted for every (box source, method) within one ``shared_fits``: the methods of a box source share
their boxes, and most vehicles are fitted alike by several."""

from __future__ import annotations

import time
from collections import defaultdict
from functools import partial

from deepword.footprint import (
    FootprintPrior,
    facing_trust,
    frame_footprints,
    refuse_weighed,
    shared_fits,
)
from deepword.frame_processes import frame_processes, map_frames
from deepword.progress import progress_lines
from deepword.word_format import Record

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


def _fit_frame(frame_jobs: dict, prior: FootprintPrior, radius_m: float) -> dict:
    """{job: (its estimates, their fused footprints)} of one frame (``frame_jobs``: {job: (the frame's views,
    use_relations)}), the jobs' fits shared (``shared_fits``)."""
    with shared_fits():
        return {key: frame_footprints(views, prior, radius_m, use_relations)
                for key, (views, use_relations) in frame_jobs.items()}


def fused_footprints(jobs: Jobs, frames: list[int], prior: FootprintPrior, radius_m: float,
                     workers: int = 1, frames_per_task: int | None = None,
                     facing_val_accuracy: float | None = None, desc: str = "bev: footprints"
                     ) -> tuple[dict[tuple[str, str], dict[int, list]], dict[str, float]]:
    """{job: {frame: [(footprint, its estimates), ...]}} for every job and every frame of ``frames`` (a frame none
    of a job's views fall in gets none), keyed in the order of ``frames``, and {box source: the weight its facing votes
    were given}; ``workers`` > 1: up to that many spawned processes, ``frames_per_task`` frames a task
    (``deepword.frame_processes.map_frames``; its ``FRAMES_PER_TASK`` by default). With ``facing_val_accuracy`` (the
    facing network's, 0-1) each box source's votes are weighed by ``facing_trust`` of its ``facing_lead`` job's
    footprints, and where that is under 1 its methods' frames are fused again with the weighed votes. ``desc`` leads
    the progress lines."""
    started = time.perf_counter()
    order = sorted(frames)
    fitted = map_frames(partial(_fit_frame, prior=prior, radius_m=radius_m),
                        [{key: (views.get(f, []), use) for key, (views, use) in jobs.items()} for f in order],
                        workers, partial(progress_lines, desc=desc, unit="frame"), frames_per_task)
    out = {key: {f: part[key] for f, part in zip(order, fitted, strict=True)} for key in jobs}
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
    processes = frame_processes(workers, len(order), frames_per_task)
    print(f"{desc} of {len(order)} frames x {len(jobs)} (boxes, method) in "
          f"{time.perf_counter() - started:.0f} s ({processes} process{'es' if processes > 1 else ''})"
          + "".join(f"; {b} boxes' facing votes x {w:.2f}" for b, w in trust.items() if w < 1.0), flush=True)
    return {key: {f: fused[f][1] for f in frames} for key, fused in out.items()}, trust
