"""The detector's operating point: one score threshold and one minimum box side per class, chosen on the val
split by the end-to-end pair_f1 (``CRITERION``) of the bundle's end-to-end method (the shipped relation model, with the IoU rule for
the wheels it leaves unclaimed by default: ``export.end_to_end``), and stored in the bundle's ``export.json``.

Every detection down to the detector's ``score_threshold`` (0.1) is worth keeping for AP, which integrates
over all scores; a relation network fed all of them sees dozens of weak boxes per image, and each weak
vehicle box that overlaps a real one can take its wheels. What to keep is a trade-off between missed and
false boxes that only the end-to-end metric can weigh, and the two classes weigh it differently (a false
vehicle steals wheels, a false wheel only adds one claim), hence one threshold per class.

Size is the other axis. Most of the wheels a relation model wrongly claims are boxes of a few pixels: where
nothing is, or beside a wheel too small to place within IoU 0.5. A wheel box that small is also one the
evaluation does not score as truth (``eval.min_box_px``), so keeping it can cost precision and gain nothing;
whether it does on a given detector is what the search finds out, per class (``min_side_grid``).

The search is exhaustive over the grid (coordinate ascent is not enough: keeping a weak false vehicle can be
harmless while weak wheels are dropped and harmful once they are kept, so each class's best threshold
depends on the other's), on pair_f1 as ``deepword.metrics`` scores it: the evaluate stage's own definition, on
the val split, never the test split. Among equally good points the one that keeps the most wins (the lowest
thresholds, then the lowest minimum sides: more recall for the same F1).

On a small val split (a new camera's first few dozen labelled images) the best single point is mostly noise:
thousands of points are tried on a few hundred pairs, and the winner is the one whose few lucky images went
its way. ``smoothing`` (grid steps) chooses instead the point whose neighbourhood scores best on average: the
mean criterion over the points with the same minimum sides and every class's threshold within that many
grid steps, the centre of a good plateau rather than its highest needle (``choose_point``).

A second, larger labelled set scored by the same model can steady it further: a ``Prior`` (the generator's val
split beside a new camera's few val images, ``val_prior`` of a composed dataset) adds its counts to the val
split's at every point, weighed as ``images`` val images, before the criterion is taken. The best point on the
generator's images lies near the best on another domain's (docs/detector.md), and as the new images outnumber
``images`` they decide.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np

from deepword.inference.runtime import keep_at, kept_masks
from deepword.metrics import Counts, score_image, score_records
from deepword.relation_graph import subgraph
from deepword.word_format import Record

__all__ = ["CRITERION", "DEFAULT_GRID", "OperatingPoint", "Prior", "SubsetRelation", "SubsetScores", "choose_point",
           "end_to_end_score", "keep_at", "kept_masks", "search_operating_point"]

# The one selection criterion of the operating point: the §7 metric (``deepword.metrics``, percent) of the end-to-end
# method on the val split that the search maximises; the export stage's metric keys, ``deepword tune``'s bundle
# entries and the report's labels are named after it
CRITERION = "pair_f1"
COUNT_FIELDS = tuple(f.name for f in fields(Counts))
DEFAULT_GRID = tuple(round(0.1 + 0.05 * i, 2) for i in range(13))  # 0.10 ... 0.70


def distinct_rows(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the first row of each distinct row of the boolean ``masks`` (P, n), each row's distinct row's index): rows
    packed into 64-bit words and sorted stably (``np.lexsort``); ``np.unique(axis=0)``, which sorts the rows as opaque
    bytes, took 2.4 s of the search's 2.8 on the export config's grid. A matrix without columns has one distinct
    (empty) row."""
    if masks.shape[1] == 0:
        return np.zeros(1, np.int64), np.zeros(len(masks), np.int64)
    packed = np.packbits(masks, axis=1)
    packed = np.pad(packed, ((0, 0), (0, -packed.shape[1] % 8)))
    words = np.ascontiguousarray(packed).view(np.uint64)                       # (P, words)
    order = np.lexsort(words.T[::-1])                                          # stable: the first of equals first
    ordered = words[order]
    starts = np.ones(len(order), dtype=bool)
    starts[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return order[starts], inverse


@dataclass(frozen=True)
class OperatingPoint:
    """What a detection needs to be kept: a score of at least ``thresholds[class]`` and a shorter box side of at
    least ``min_sides[class]`` image pixels."""
    thresholds: tuple[float, ...]
    min_sides: tuple[float, ...]

    def keep(self, record: Record) -> Record:
        return keep_at(record, self.thresholds, self.min_sides)


def end_to_end_score(truths: Sequence[Record], detections: Sequence[Record], point: OperatingPoint,
                       predict: Callable[[list[Record]], list[Record]], min_box_px: float,
                       match_iou: float) -> float:
    """``CRITERION`` (percent) of ``predict`` on the detections kept at ``point``, against ``truths``."""

    preds = predict([point.keep(d) for d in detections])
    return score_records(list(truths), {p.image: p for p in preds}, min_box_px, match_iou).percentages()[CRITERION]


@dataclass(frozen=True)
class Prior:
    """Labelled images whose counts join the val split's in the search, weighed as ``images`` val images.
    ``detections[i]`` are the detections of ``truths[i]``'s image, by the same detector."""
    truths: Sequence[Record]
    detections: Sequence[Record]
    images: float

    def weight(self) -> float:
        """Each prior image's counts are multiplied by this: together they weigh as ``images`` images."""
        if self.images < 0:
            raise ValueError(f"operating point: a prior weighs as >= 0 images, got {self.images}")
        return float(self.images) / len(self.truths) if self.truths else 0.0


def search_operating_point(truths: Sequence[Record], detections: Sequence[Record],
                           predict: Callable[[list[Record]], list[Record]], num_classes: int = 2,
                           grid: Sequence[float] = DEFAULT_GRID,
                           min_side_grid: Sequence[Sequence[float]] | None = None, min_box_px: float = 0.0,
                           match_iou: float = 0.5, smoothing: int = 0,
                           prior: Prior | None = None) -> tuple[OperatingPoint, dict[OperatingPoint, float]]:
    """(the operating point ``choose_point`` takes, every evaluated {point: its end-to-end ``CRITERION``}): every
    per-class threshold combination of ``grid`` with every per-class combination of ``min_side_grid[class]`` (None: no
    minimum side). ``detections[i]`` are the detections of ``truths[i]``'s image. With a ``prior``, each point's value
    is the criterion of the val counts plus the prior's, weighed (``Prior.weight``); ``predict`` decides both."""
    grid = sorted({float(t) for t in grid})
    if not grid:
        raise ValueError("operating point: the threshold grid is empty")
    sides = [[0.0]] * num_classes if min_side_grid is None else [sorted({float(s) for s in g}) for g in min_side_grid]
    if len(sides) != num_classes or not all(sides):
        raise ValueError(f"operating point: min_side_grid needs one non-empty list per class ({num_classes}), "
                         f"got {min_side_grid}")
    points = [OperatingPoint(t, m) for t in itertools.product(grid, repeat=num_classes)
              for m in itertools.product(*sides)]
    totals = SubsetScores(truths, detections, predict, min_box_px, match_iou).totals(points).astype(np.float64)
    if prior is not None and prior.truths:
        prior_totals = SubsetScores(prior.truths, prior.detections, predict, min_box_px, match_iou).totals(points)
        totals += prior.weight() * prior_totals
    seen = dict(zip(points, criterion_of(totals), strict=True))
    return choose_point(seen, smoothing), seen


def criterion_of(totals: np.ndarray) -> list[float]:
    """``CRITERION`` (percent) of each row of count totals (points x ``COUNT_FIELDS``; weighed counts may be
    fractional)."""
    return [Counts(**dict(zip(COUNT_FIELDS, row.tolist(), strict=True))).percentages()[CRITERION] for row in totals]


def neighbourhood_means(seen: dict[OperatingPoint, float], radius: int) -> dict[OperatingPoint, float]:
    """Each point's mean value over the points of ``seen`` with its minimum sides and every threshold within
    ``radius`` steps of the threshold grid (``seen``'s thresholds, sorted) of its own."""
    grid = {t: i for i, t in enumerate(sorted({t for p in seen for t in p.thresholds}))}
    by_sides: dict[tuple, list[OperatingPoint]] = {}
    for p in seen:
        by_sides.setdefault(p.min_sides, []).append(p)
    out = {}
    for points in by_sides.values():
        steps = np.array([[grid[t] for t in p.thresholds] for p in points])
        values = np.array([seen[p] for p in points])
        near = (np.abs(steps[:, None, :] - steps[None, :, :]) <= radius).all(axis=2)
        out |= dict(zip(points, (near @ values) / near.sum(axis=1), strict=True))
    return out


def choose_point(seen: dict[OperatingPoint, float], smoothing: int = 0) -> OperatingPoint:
    """The point of ``seen`` with the best value (``smoothing`` > 0: the best mean over its neighbourhood of that
    many threshold grid steps, ``neighbourhood_means``); among equals the one that keeps the most (lowest
    thresholds, then lowest minimum sides)."""
    if smoothing < 0:
        raise ValueError(f"operating point: smoothing must be >= 0 grid steps, got {smoothing}")
    score = seen if smoothing == 0 else neighbourhood_means(seen, smoothing)
    best = max(score.values())
    return min((p for p, value in score.items() if value >= best - 1e-9),
               key=lambda p: (sum(p.thresholds), p.thresholds, sum(p.min_sides), p.min_sides))


class SubsetScores:
    """``end_to_end_score`` of many operating points, each image scored once per distinct subset of its boxes.

    Thousands of points keep only a few distinct subsets of each image's detections, and an image's §7 counts
    depend on nothing else (``predict`` must decide an image from its kept boxes alone, as ``SubsetRelation``
    does): so each distinct subset is predicted and counted once, remembered by (image, kept boxes), and a point
    costs a mask per image and a sum. Scored afresh per point, matching boxes for the counts took two thirds of
    the search, and the relation model ran on a few new subsets at a time instead of full batches."""

    def __init__(self, truths: Sequence[Record], detections: Sequence[Record],
                 predict: Callable[[list[Record]], list[Record]], min_box_px: float, match_iou: float):
        if len(truths) != len(detections):
            raise ValueError(f"operating point: {len(truths)} labelled images but {len(detections)} detection records")
        self.truths, self.detections, self.predict = list(truths), list(detections), predict
        self.min_box_px, self.match_iou = min_box_px, match_iou
        self.counts: dict[tuple[int, bytes], Counts] = {}

    def scores(self, points: Sequence[OperatingPoint]) -> list[float]:
        """``CRITERION`` (percent) at each of ``points`` (``totals``)."""
        return criterion_of(self.totals(points)) if points else []

    def totals(self, points: Sequence[OperatingPoint]) -> np.ndarray:
        """The §7 counts summed over the images at each of ``points``: (points, ``COUNT_FIELDS``) integers. The
        subsets no point scored before go to ``predict`` in one
        call, in the order the points first keep them (point by point, image by image), so that it can batch them
        however it likes. Each image's masks at all points are one array operation, and a point's counts are one row
        of a sum over images: the loop over points x images it replaces took 37-39x as long on the export
        config's grid (``benchmarks/bench_operating_point.py``)."""
        if not points:
            return np.zeros((0, len(COUNT_FIELDS)), dtype=np.int64)
        thresholds = np.array([p.thresholds for p in points], dtype=np.float64)   # (P, classes)
        min_sides = np.array([p.min_sides for p in points], dtype=np.float64)
        keys: list[tuple[int, bytes]] = []     # a subset of one image's boxes: (image index, kept mask's bytes)
        first: list[int] = []                  # the first point that keeps it
        slot = np.empty((len(self.detections), len(points)), dtype=np.int64)   # image x point -> index into keys
        for i, d in enumerate(self.detections):
            masks = kept_masks(d, thresholds, min_sides)                        # (P, boxes)
            first_point, inverse = distinct_rows(masks)
            slot[i] = len(keys) + inverse
            keys += [(i, masks[p].tobytes()) for p in first_point]
            first += first_point.tolist()
        new = sorted((k for k, key in enumerate(keys) if key not in self.counts), key=lambda k: (first[k], keys[k][0]))
        if new:
            preds = self.predict([points[first[k]].keep(self.detections[keys[k][0]]) for k in new])
            for k, pred in zip(new, preds, strict=True):
                i = keys[k][0]
                self.counts[keys[k]] = score_image(self.truths[i], pred, self.min_box_px, self.match_iou)
        table = np.array([[getattr(self.counts[key], name) for name in COUNT_FIELDS] for key in keys],
                         dtype=np.int64)                                                  # (subsets, count fields)
        return table[slot].sum(axis=0)                                                      # (P, count fields)


class SubsetRelation:
    """DeepWORD on subsets of each image's detections, building every image's graph once.

    A graph's nodes are its boxes' crops and their pairwise priors, candidates and adjacency, each a function
    of its own box or its own pair only, so the graph of a subset of the boxes is the full graph with the
    other nodes' rows and columns removed. The search runs the relation model on many subsets of the same
    detections; cropping them once makes it a matter of relation-model calls, and since many operating points
    keep the same boxes of an image, each distinct subset is run once and remembered.

    With ``embed`` (called once with {image: graph}, it returns an object with ``batch_size`` and
    ``scores(images, box_ids)``: the export stage passes ``stages.export.embedded_boxes.EmbeddedBoxes`` over the torch
    network the bundle's relation model was exported from) the backbone, nearly all of the model's cost, runs once
    per box too, and a subset costs only the graph part; without it every subset goes to ``relation`` (``OnnxRelation``) whole. ``progress(done, total)``
    is called after each batch of new subsets."""

    def __init__(self, relation, detections: Sequence[Record], load_rgb: Callable[[Record], np.ndarray],
                 batch_size: int = 16, embed: Callable[[dict], object] | None = None,
                 progress: Callable[[int, int], None] | None = None):
        self.relation, self.batch_size, self.progress = relation, batch_size, progress
        self.predicted: dict[tuple[str, tuple[int, ...]], Record] = {}
        self.graphs = {d.image: relation.graph(d, load_rgb(d)) for d in detections}
        # a detection record's box ids are its rows (detections_to_record numbers them 0..N-1)
        for d in detections:
            if not np.array_equal(d.box_ids, np.arange(len(d.boxes))):
                raise ValueError(f"{d.image}: detection box ids must be 0..N-1 (as detections_to_record writes them)")
        self.embedded = None
        if embed is not None:
            self.embedded = embed(self.graphs)
            self.batch_size = self.embedded.batch_size

    def subgraph(self, record: Record):
        return subgraph(self.graphs[record.image], record.box_ids)

    def __call__(self, records: list[Record]) -> list[Record]:
        keys = [(r.image, tuple(int(i) for i in r.box_ids)) for r in records]
        pending = list({k: r for k, r in zip(keys, records, strict=True) if k not in self.predicted}.items())
        pending.sort(key=lambda item: len(item[0][1]))  # batches of like sizes: less padding
        for start in range(0, len(pending), self.batch_size):
            part = pending[start:start + self.batch_size]
            chunk = [r for _, r in part]
            if self.embedded is None:
                preds = self.relation.predict_graphs(chunk, [self.subgraph(r) for r in chunk])
            else:
                preds = self.relation.decide(chunk, self.embedded.scores([r.image for r in chunk],
                                                                         [r.box_ids for r in chunk]))
            self.predicted.update(zip((k for k, _ in part), preds, strict=True))
            if self.progress is not None:
                self.progress(start + len(part), len(pending))
        return [self.predicted[k] for k in keys]
