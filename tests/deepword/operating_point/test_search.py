import dataclasses
import itertools
from dataclasses import replace

import numpy as np
import pytest

from deepword.geometry import containment
from deepword.metrics import score_records
from deepword.operating_point.search import (
    OperatingPoint,
    Prior,
    SubsetRelation,
    choose_point,
    end_to_end_score,
    keep_at,
    search_operating_point,
)
from deepword.word_format import Record


def record(boxes, relations=()) -> Record:
    return Record(image="images/front/000001.png", frame_id=1, camera="front", width=200, height=100,
                  boxes=np.asarray(boxes, dtype=np.float64), relations=list(relations), wheel_pairs=[])


# one vehicle with two wheels
TRUTH = record([[10, 10, 110, 70, 1.0, 0, 0], [15, 50, 35, 70, 1.0, 1, 1], [85, 50, 105, 70, 1.0, 1, 2]],
               [(0, 1, None), (0, 2, None)])
# the vehicle and its wheels found (one wheel weakly), a weak false vehicle that holds the weak wheel more
# tightly than the true one, and a weaker false wheel inside the true vehicle
DETECTIONS = record([[10, 10, 110, 70, 0.9, 0, 0], [15, 50, 35, 70, 0.8, 1, 1], [85, 50, 105, 70, 0.35, 1, 2],
                     [80, 40, 160, 75, 0.45, 0, 3], [50, 50, 70, 70, 0.25, 1, 4]])


def tightest_vehicle(records: list[Record]) -> list[Record]:
    """A stand-in relation model: each wheel to the smallest vehicle box that holds it."""
    out = []
    for rec in records:
        vehicles, wheels = rec.boxes[rec.class_ids == 0], rec.boxes[rec.class_ids == 1]
        relations = []
        if len(vehicles):
            held = containment(wheels[:, :4], vehicles[:, :4]) >= 0.99
            area = (vehicles[:, 2] - vehicles[:, 0]) * (vehicles[:, 3] - vehicles[:, 1])
            for w, row in zip(wheels, held, strict=True):
                if row.any():
                    v = vehicles[np.flatnonzero(row)[np.argmin(area[row])]]
                    relations.append((int(v[6]), int(w[6]), None))
        out.append(replace(rec, relations=relations))
    return out


def test_keep_at_applies_one_threshold_per_class_and_keeps_ids():
    kept = keep_at(DETECTIONS, (0.5, 0.3))
    assert kept.box_ids.tolist() == [0, 1, 2] and kept.relations == []


def test_keep_at_drops_boxes_under_their_class_minimum_side():
    kept = keep_at(DETECTIONS, (0.1, 0.1), (0.0, 20.0))      # every wheel is 20 px; the vehicles stay
    assert kept.box_ids.tolist() == [0, 1, 2, 3, 4]
    kept = keep_at(DETECTIONS, (0.1, 0.1), (0.0, 20.5))
    assert kept.box_ids.tolist() == [0, 3]


def no_sides(thresholds) -> OperatingPoint:
    return OperatingPoint(tuple(thresholds), (0.0, 0.0))


def test_chosen_thresholds_maximise_val_pair_f1():
    grid = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    chosen, seen = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid)
    every = {no_sides(t): end_to_end_score([TRUTH], [DETECTIONS], no_sides(t), tightest_vehicle, 0.0, 0.5)
             for t in itertools.product(grid, repeat=2)}
    assert seen == pytest.approx(every)
    assert every[chosen] == max(every.values()) == 100.0
    # the false vehicle (0.45) must go and the weak true wheel (0.35) stay, the false wheel (0.25) go
    assert chosen == no_sides((0.5, 0.3))
    # keeping everything, as before the operating point, loses a wheel to the false vehicle and adds one
    assert every[no_sides((0.1, 0.1))] < 70.0


# the same vehicle, its weak true wheel scored 0.22 and nothing false: a wheel threshold above 0.2 loses that wheel
PRIOR_DETECTIONS = record([[10, 10, 110, 70, 0.9, 0, 0], [15, 50, 35, 70, 0.8, 1, 1], [85, 50, 105, 70, 0.22, 1, 2]])


def test_a_prior_adds_its_weighed_counts_and_moves_the_point_as_it_outweighs_val():
    grid = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    alone, seen_alone = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid)
    # val needs the wheel threshold at 0.3 (its false wheel scores 0.25); the prior needs it at 0.2 at most
    assert alone == no_sides((0.5, 0.3))
    unweighed, seen_zero = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid,
                                                  prior=Prior([TRUTH], [PRIOR_DETECTIONS], 0.0))
    assert unweighed == alone and seen_zero == pytest.approx(seen_alone)

    def pooled(point, weight):   # the criterion of val's counts plus the prior's, by hand
        val = score_records([TRUTH], {TRUTH.image: tightest_vehicle([point.keep(DETECTIONS)])[0]}, 0.0, 0.5)
        pri = score_records([TRUTH], {TRUTH.image: tightest_vehicle([point.keep(PRIOR_DETECTIONS)])[0]}, 0.0, 0.5)
        return dataclasses.replace(val, **{f.name: getattr(val, f.name) + weight * getattr(pri, f.name)
                                           for f in dataclasses.fields(val)}).percentages()["pair_f1"]

    # two prior images weighed as ten: five times each one's counts
    heavy, seen_heavy = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid,
                                               prior=Prior([TRUTH, TRUTH], [PRIOR_DETECTIONS] * 2, 10.0))
    assert seen_heavy == pytest.approx({p: pooled(p, 10.0) for p in seen_heavy})
    assert heavy == no_sides((0.5, 0.1))   # 0.1 and 0.2 keep the same wheels: the one that keeps the most
    light, _ = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid,
                                      prior=Prior([TRUTH], [PRIOR_DETECTIONS], 0.1))
    assert light == alone
    with pytest.raises(ValueError, match="a prior weighs as >= 0 images"):
        search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid,
                               prior=Prior([TRUTH], [PRIOR_DETECTIONS], -1.0))


# a tiny false wheel scored above the weak true one: no wheel threshold keeps the true wheel and drops it
SMALL_FALSE = record([[10, 10, 110, 70, 0.9, 0, 0], [15, 50, 35, 70, 0.8, 1, 1], [85, 50, 105, 70, 0.35, 1, 2],
                      [60, 62, 65, 67, 0.6, 1, 3]])


def test_the_minimum_side_drops_a_small_false_wheel_a_threshold_cannot():
    grid = [0.1, 0.3, 0.5, 0.7]
    thresholds_only, seen_t = search_operating_point([TRUTH], [SMALL_FALSE], tightest_vehicle, 2, grid)
    assert seen_t[thresholds_only] < 100.0
    chosen, seen = search_operating_point([TRUTH], [SMALL_FALSE], tightest_vehicle, 2, grid,
                                          [[0.0], [0.0, 4.0, 8.0, 25.0]])
    assert len(seen) == 16 * 4 and seen[chosen] == max(seen.values()) == 100.0
    # the lowest thresholds and the smallest minimum side that get there: the 5 px wheel goes, the 20 px ones stay
    assert chosen == OperatingPoint((0.1, 0.1), (0.0, 8.0))
    with pytest.raises(ValueError, match="one non-empty list per class"):
        search_operating_point([TRUTH], [SMALL_FALSE], tightest_vehicle, 2, grid, [[0.0]])


def test_subset_relation_runs_each_distinct_subset_once():
    calls = []

    class CountingRelation:
        def graph(self, record, rgb):
            from deepword.relation_graph import ImageGraph
            n = len(record.boxes)
            return ImageGraph(crops=np.zeros((n, 3, 2, 2), np.uint8), coords=np.zeros((n, 4)), classes=record.class_ids,
                              valid=np.ones(n, bool), adj=np.zeros((n, n)), cand=np.zeros((n, n), bool))

        def predict_graphs(self, records, graphs):
            calls.extend(tuple(r.box_ids.tolist()) for r in records)
            return tightest_vehicle(records)

    relation = SubsetRelation(CountingRelation(), [DETECTIONS], lambda rec: None)
    search_operating_point([TRUTH], [DETECTIONS], relation, 2, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    assert len(calls) == len(set(calls)) == len(relation.predicted) < 36


def test_masks_at_many_points_are_each_points_own_mask():
    from deepword.inference.runtime import kept_mask, kept_masks

    points = [OperatingPoint(t, m) for t in itertools.product([0.1, 0.3, 0.5, 0.9], repeat=2)
              for m in itertools.product([0.0, 30.0], [0.0, 8.0, 25.0])]
    thresholds = np.array([p.thresholds for p in points])
    sides = np.array([p.min_sides for p in points])
    for rec in (DETECTIONS, SMALL_FALSE, replace(DETECTIONS, boxes=DETECTIONS.boxes[:0])):
        masks = kept_masks(rec, thresholds, sides)
        assert masks.shape == (len(points), len(rec.boxes))
        for p, row in zip(points, masks, strict=True):
            assert np.array_equal(row, kept_mask(rec, p.thresholds, p.min_sides))


def test_distinct_rows_are_first_occurrences_and_every_row_maps_to_its_equal():
    from deepword.operating_point.search import distinct_rows

    rng = np.random.default_rng(0)
    for n in (1, 7, 64, 65, 130):
        masks = rng.random((300, n)) < 0.9   # narrow rows repeat, wide ones seldom
        first, inverse = distinct_rows(masks)
        assert len(first) == len(np.unique(masks, axis=0))
        assert all(np.array_equal(masks[first[inverse[p]]], masks[p]) for p in range(len(masks)))
        assert all(not any(np.array_equal(masks[q], masks[f]) for q in range(f)) for f in first)
    first, inverse = distinct_rows(np.zeros((5, 0), dtype=bool))
    assert first.tolist() == [0] and inverse.tolist() == [0] * 5


def test_an_image_without_detections_scores_as_its_truth_says():
    rear = "images/rear/000001.png"
    truths = [TRUTH, replace(TRUTH, image=rear)]
    detections = [DETECTIONS, replace(DETECTIONS, image=rear, boxes=DETECTIONS.boxes[:0])]
    _, seen = search_operating_point(truths, detections, tightest_vehicle, 2, [0.1, 0.5])
    assert seen == pytest.approx({p: end_to_end_score(truths, detections, p, tightest_vehicle, 0.0, 0.5) for p in seen})
    assert max(seen.values()) < 100.0   # the rear image's pairs are all missed


def test_empty_grid_is_an_error():
    with pytest.raises(ValueError, match="grid is empty"):
        search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, [])


def test_the_search_predicts_and_scores_each_distinct_subset_once_and_agrees_with_scoring_afresh(monkeypatch):
    import deepword.operating_point.search as op

    scored, batches, real_score = [], [], op.score_image

    def counting_score(gt, pred, *args):
        scored.append((pred.image, tuple(pred.box_ids.tolist())))
        return real_score(gt, pred, *args)

    def predict(records):
        batches.append([(r.image, tuple(r.box_ids.tolist())) for r in records])
        return tightest_vehicle(records)

    monkeypatch.setattr(op, "score_image", counting_score)
    rear = "images/rear/000001.png"
    truths = [TRUTH, replace(TRUTH, image=rear)]
    detections = [DETECTIONS, replace(SMALL_FALSE, image=rear)]
    grid, sides = [0.1, 0.3, 0.5, 0.7], [[0.0, 30.0], [0.0, 8.0]]
    chosen, seen = search_operating_point(truths, detections, predict, 2, grid, sides)
    assert len(seen) == 16 * 4
    # one call of the relation model for the whole search, every image's distinct subsets in it once, each scored once
    assert len(batches) == 1 and len(batches[0]) == len(set(batches[0])) == len(scored) == len(set(scored))
    assert len(scored) < 2 * len(seen)
    assert seen == pytest.approx({p: end_to_end_score(truths, detections, p, tightest_vehicle, 0.0, 0.5)
                                  for p in seen})
    assert seen[chosen] == max(seen.values()) == 100.0


def test_smoothing_chooses_the_centre_of_a_plateau_over_a_lone_peak():
    """A lone needle at (0.1, 0.1) beats a broad plateau point by point; averaged over each point's neighbours
    within one grid step the plateau's centre wins."""
    grid = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    seen = {OperatingPoint((a, b), (0.0, 0.0)): 50.0 for a in grid for b in grid}
    seen[OperatingPoint((0.1, 0.1), (0.0, 0.0))] = 90.0
    for a in (0.3, 0.4, 0.5):
        for b in (0.3, 0.4, 0.5):
            seen[OperatingPoint((a, b), (0.0, 0.0))] = 80.0
    seen[OperatingPoint((0.4, 0.4), (0.0, 0.0))] = 82.0
    assert choose_point(seen) == OperatingPoint((0.1, 0.1), (0.0, 0.0))
    assert choose_point(seen, smoothing=1) == OperatingPoint((0.4, 0.4), (0.0, 0.0))
    # neighbours share the minimum sides: a plateau at other sides does not lift this one
    other = {OperatingPoint(p.thresholds, (8.0, 0.0)): 0.0 for p in seen}
    assert choose_point(seen | other, smoothing=1) == OperatingPoint((0.4, 0.4), (0.0, 0.0))
    with pytest.raises(ValueError, match="smoothing must be >= 0"):
        choose_point(seen, smoothing=-1)


def test_search_passes_smoothing_to_the_choice():
    grid = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    chosen, seen = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid)
    smoothed, _ = search_operating_point([TRUTH], [DETECTIONS], tightest_vehicle, 2, grid, smoothing=1)
    assert chosen == choose_point(seen) and smoothed == choose_point(seen, 1)
