"""The operating-point search's bookkeeping: which boxes each point keeps on each image, and each point's counts.

The export stage (and ``deepword tune``) score thousands of operating points (thresholds x minimum sides per class)
on the val split; every distinct subset of an image's boxes is predicted and counted once, and a point is then the
sum of its images' counts. ``SubsetScores.scores`` computes each image's masks at every point in one array operation
and the sums as one indexed sum; the reference is the per-point loop it replaced (``kept_mask`` per point and image, a
``Counts`` addition per point and image). Both run here on the same synthetic detections, with every subset's counts
already known, so only the bookkeeping is timed; the two must give the same scores. Prints both and their ratio.

    python -m benchmarks.bench_operating_point [--images 106] [--boxes 20] [--rounds 3]
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from deepword.inference.runtime import kept_mask
from deepword.metrics import Counts
from deepword.operating_point.search import CRITERION, OperatingPoint, SubsetScores
from deepword.word_format import Record

EXPORT_CONFIG = Path(__file__).resolve().parents[1] / "conf" / "export" / "default.yaml"


def export_points() -> list[OperatingPoint]:
    """The default export config's grid: every per-class threshold pair with every per-class minimum side pair."""
    op = OmegaConf.load(EXPORT_CONFIG).operating_point
    sides = [list(op.min_side_grid[c]) for c in ("vehicle", "wheel")]
    return [OperatingPoint(t, m) for t in itertools.product(list(op.grid), repeat=2) for m in itertools.product(*sides)]


def detections(images: int, boxes: int, seed: int = 0) -> list[Record]:
    """Random detections of both classes, scores 0.1-1 and shorter sides 2-60 px, as a detector's at 640x480."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(images):
        x1, y1 = rng.uniform(0, 560, boxes), rng.uniform(0, 400, boxes)
        w, h = rng.uniform(2, 80, boxes), rng.uniform(2, 60, boxes)
        table = np.column_stack([x1, y1, x1 + w, y1 + h, rng.uniform(0.1, 1.0, boxes), rng.integers(0, 2, boxes),
                                 np.arange(boxes)])
        out.append(Record(image=f"images/front/{i:06d}.png", frame_id=i, camera="front", width=640, height=480,
                          boxes=table, relations=[], wheel_pairs=[]))
    return out


def per_point_loop(search: SubsetScores, points: list[OperatingPoint]) -> list[float]:
    """The reference: a mask per point and image, then a sum of ``Counts`` per point (subsets already counted)."""
    keys = [[(i, kept_mask(d, p.thresholds, p.min_sides).tobytes()) for i, d in enumerate(search.detections)]
            for p in points]
    return [sum((search.counts[k] for k in point_keys), Counts()).percentages()[CRITERION] for point_keys in keys]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", type=int, default=106, help="val images (the quick profile's val split: ~106)")
    parser.add_argument("--boxes", type=int, default=20, help="detections an image")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    points, dets = export_points(), detections(args.images, args.boxes)
    search = SubsetScores(dets, dets, lambda records: records, 0.0, 0.5)   # no relations: the counts are cheap
    search.scores(points)   # every subset predicted and counted once; both timings below start from here
    loop, arrays = [], []
    for _ in range(args.rounds):   # interleaved, so that a change of the host's load falls on both
        start = time.perf_counter()
        reference = per_point_loop(search, points)
        loop.append(time.perf_counter() - start)
        start = time.perf_counter()
        vectorised = search.scores(points)
        arrays.append(time.perf_counter() - start)
    if reference != vectorised:
        raise AssertionError("the per-point loop and SubsetScores.scores disagree")
    ref, new = float(np.median(loop)), float(np.median(arrays))
    print(f"{len(points)} operating points x {args.images} images of {args.boxes} detections; "
          f"{len(search.counts)} distinct subsets")
    print(f"per-point loop (reference):     {ref:6.2f} s")
    print(f"SubsetScores.scores (arrays):   {new:6.2f} s")
    print(f"speed-up: {ref / new:.1f}x")


if __name__ == "__main__":
    main()
