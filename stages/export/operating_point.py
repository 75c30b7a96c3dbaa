"""The detector's operating point: one score threshold per class, chosen on the val split by the end-to-end
pair_f1 of the shipped relation model, and stored in the bundle's ``export.json``.

Every detection down to the detector's ``score_threshold`` (0.1) is worth keeping for AP, which integrates
over all scores; a relation network fed all of them sees dozens of weak boxes per image, and each weak
vehicle box that overlaps a real one can take its wheels. What to keep is a trade-off between missed and
false boxes that only the end-to-end metric can weigh, and the two classes weigh it differently (a false
vehicle steals wheels, a false wheel only adds one claim), hence one threshold per class.

The search is exhaustive over a grid of threshold pairs (coordinate ascent is not enough: keeping a weak
false vehicle can be harmless while weak wheels are dropped and harmful once they are kept, so each class's
best threshold depends on the other's), on pair_f1 as ``stages.metrics`` scores it: the evaluate
stage's own definition, on the val split, never the test split. Among equally good pairs the one with the
lowest thresholds wins (more recall for the same F1).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import numpy as np

from stages.inference.runtime import keep_at
from stages.word_format import Record

__all__ = ["DEFAULT_GRID", "SubsetRelation", "choose_thresholds", "end_to_end_pair_f1", "keep_at"]

DEFAULT_GRID = tuple(round(0.1 + 0.05 * i, 2) for i in range(13))  # 0.10 ... 0.70


def end_to_end_pair_f1(truths: Sequence[Record], detections: Sequence[Record], thresholds: Sequence[float],
                       predict: Callable[[list[Record]], list[Record]], min_box_px: float,
                       match_iou: float) -> float:
    """pair_f1 (percent) of ``predict`` on the detections kept at ``thresholds``, against ``truths``."""
    from stages.metrics import score_records

    preds = predict([keep_at(d, thresholds) for d in detections])
    return score_records(list(truths), {p.image: p for p in preds}, min_box_px, match_iou).percentages()["pair_f1"]


def choose_thresholds(truths: Sequence[Record], detections: Sequence[Record],
                      predict: Callable[[list[Record]], list[Record]], num_classes: int = 2,
                      grid: Sequence[float] = DEFAULT_GRID, min_box_px: float = 0.0,
                      match_iou: float = 0.5) -> tuple[tuple[float, ...], dict[tuple[float, ...], float]]:
    """(the per-class thresholds on ``grid`` maximising end-to-end pair_f1, every evaluated
    {thresholds: pair_f1}). ``detections[i]`` are the detections of ``truths[i]``'s image."""
    grid = sorted({float(t) for t in grid})
    if not grid:
        raise ValueError("choose_thresholds: the threshold grid is empty")
    seen = {t: end_to_end_pair_f1(truths, detections, t, predict, min_box_px, match_iou)
            for t in itertools.product(grid, repeat=num_classes)}
    best = max(seen.values())
    chosen = min((t for t, f1 in seen.items() if f1 == best), key=lambda t: (sum(t), t))
    return chosen, seen


class SubsetRelation:
    """DeepWORD on subsets of each image's detections, building every image's graph once.

    A graph's nodes are its boxes' crops and their pairwise priors, candidates and adjacency, each a function
    of its own box or its own pair only, so the graph of a subset of the boxes is the full graph with the
    other nodes' rows and columns removed. The threshold search runs the relation model on many subsets of
    the same detections; cropping them once makes it a matter of onnxruntime calls."""

    def __init__(self, relation, detections: Sequence[Record], load_rgb: Callable[[Record], np.ndarray],
                 batch_size: int = 16):
        self.relation, self.batch_size = relation, batch_size
        self.graphs = {d.image: relation.graph(d, load_rgb(d)) for d in detections}
        # a detection record's box ids are its rows (detections_to_record numbers them 0..N-1)
        for d in detections:
            if not np.array_equal(d.box_ids, np.arange(len(d.boxes))):
                raise ValueError(f"{d.image}: detection box ids must be 0..N-1 (as detections_to_record writes them)")

    def subgraph(self, record: Record):
        from stages.relation.inputs import ImageGraph

        g, idx = self.graphs[record.image], record.box_ids.astype(int)
        pairs = np.ix_(idx, idx)
        return ImageGraph(crops=g.crops[idx], coords=g.coords[idx], classes=g.classes[idx], valid=g.valid[idx],
                          adj=g.adj[pairs], cand=g.cand[pairs])

    def __call__(self, records: list[Record]) -> list[Record]:
        out = []
        for start in range(0, len(records), self.batch_size):
            chunk = records[start:start + self.batch_size]
            out += self.relation.predict_graphs(chunk, [self.subgraph(r) for r in chunk])
        return out
