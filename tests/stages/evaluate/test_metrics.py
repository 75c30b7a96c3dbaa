"""§7 metrics on hand-made cases."""

import numpy as np
import pytest

from stages.metrics import Counts, match_boxes, score_image, score_records
from stages.word_format import Record


def rec(boxes, relations=(), pairs=(), image="a.png"):
    b = np.array([list(map(float, x)) for x in boxes], dtype=np.float64).reshape(-1, 7)
    return Record(image=image, frame_id=0, camera="front", width=200, height=100, boxes=b,
                  relations=[tuple(r) if len(r) == 3 else (r[0], r[1], None) for r in relations],
                  wheel_pairs=[tuple(p) for p in pairs])


# vehicle 0 with wheels 1, 2 (a couple); wheel 3 belongs to no vehicle
GT = rec([[0, 0, 100, 50, 1, 0, 0], [5, 30, 25, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2],
          [150, 30, 170, 50, 1, 1, 3]], relations=[(0, 1), (0, 2)], pairs=[(1, 2)])


def with_relations(relations, pairs=()):
    return rec(GT.boxes.tolist(), relations, pairs)


def test_perfect_prediction():
    m = score_image(GT, with_relations([(0, 1), (0, 2)], [(2, 1)])).percentages()  # couple order ignored
    assert m == {"wheel_acc": 100.0, "pair_precision": 100.0, "pair_recall": 100.0, "pair_f1": 100.0,
                 "couple_f1": 100.0, "image_acc": 100.0}


def test_wheel_without_owner_must_be_predicted_without_owner():
    c = score_image(GT, with_relations([(0, 1), (0, 2), (0, 3)]))
    assert (c.wheels, c.wheels_correct, c.images_correct) == (3, 2, 0)
    assert (c.pair_tp, c.pair_fp, c.pair_fn) == (2, 1, 0)
    assert c.percentages()["pair_precision"] == pytest.approx(200 / 3)


def test_missed_relation_and_no_couples():
    c = score_image(GT, with_relations([(0, 1)]))
    assert (c.wheels_correct, c.pair_tp, c.pair_fn, c.couple_fn) == (2, 1, 1, 1)
    m = c.percentages()
    assert m["wheel_acc"] == pytest.approx(200 / 3) and m["pair_recall"] == 50.0 and m["couple_f1"] == 0.0


def test_duplicate_prediction_is_a_false_positive():
    c = score_image(GT, with_relations([(0, 1), (0, 1), (0, 2)]))
    assert (c.pair_tp, c.pair_fp, c.wheels_correct) == (2, 1, 3)


def test_prediction_to_a_missing_box_is_wrong():
    c = score_image(GT, with_relations([(0, 1), (99, 2)]))  # vehicle 99 does not exist
    assert (c.pair_tp, c.pair_fp, c.wheels_correct, c.images_correct) == (1, 1, 2, 0)


def test_wheel_with_two_owners_is_wrong():
    two = rec(GT.boxes.tolist() + [[0, 0, 60, 50, 1, 0, 7]], [(0, 1), (7, 1), (0, 2)])
    c = score_image(rec(GT.boxes.tolist() + [[120, 0, 199, 50, 1, 0, 7]], [(0, 1), (0, 2)]), two)
    assert c.wheels_correct == 2  # wheel 1 given to 0 and 7: wrong; wheels 2, 3 right


def test_image_without_vehicles_or_wheels_is_defined():
    empty = rec([])
    c = score_image(empty, empty)
    assert (c.images, c.images_correct, c.wheels) == (1, 1, 0)
    assert c.percentages() == {"wheel_acc": 100.0, "pair_precision": 100.0, "pair_recall": 100.0,
                               "pair_f1": 100.0, "couple_f1": 100.0, "image_acc": 100.0}
    wheels_only = rec([[5, 30, 25, 50, 1, 1, 1]])
    assert score_image(wheels_only, wheels_only).percentages()["wheel_acc"] == 100.0
    m = Counts().percentages()
    assert not any(np.isnan(v) for v in m.values())


def test_small_wheels_are_not_evaluated_and_predictions_on_them_ignored():
    small = rec([[0, 0, 100, 50, 1, 0, 0], [5, 45, 9, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2]],
                relations=[(0, 1), (0, 2)])
    pred = rec(small.boxes.tolist(), [(0, 2)])
    c = score_image(small, pred, min_box_px=8)
    assert (c.wheels, c.wheels_correct, c.pair_fn, c.pair_fp) == (1, 1, 0, 0)


def test_matching_detected_boxes_greedy_by_score():
    det = rec([[2, 1, 101, 52, 0.9, 0, 10],      # vehicle 0
               [6, 31, 25, 50, 0.8, 1, 11],      # wheel 1
               [5, 30, 24, 49, 0.3, 1, 12],      # duplicate of wheel 1, lower score: unmatched
               [76, 30, 96, 51, 0.7, 1, 13],     # wheel 2
               [140, 0, 160, 10, 0.9, 1, 14]])   # nothing there
    assert match_boxes(GT, det) == {10: 0, 11: 1, 13: 2}
    assert match_boxes(GT, GT) == {0: 0, 1: 1, 2: 2, 3: 3}  # identity on ground-truth boxes
    pred = rec(det.boxes.tolist(), [(10, 11), (10, 12), (10, 13)], [(11, 13)])
    c = score_image(GT, pred)
    # wheel 3 was not detected: wrong although it has no owner; the duplicate's relation is a false positive
    assert (c.wheels_correct, c.pair_tp, c.pair_fp, c.couple_tp) == (2, 2, 1, 1)


def test_detected_class_must_agree():
    det = rec([[0, 0, 100, 50, 0.9, 1, 10]])  # a "wheel" on the vehicle box: no match across classes
    assert match_boxes(GT, det) == {}


def test_unmatched_owner_is_wrong():
    det = rec([[150, 0, 199, 60, 0.9, 0, 10], [5, 30, 25, 50, 0.8, 1, 11]])
    c = score_image(GT, rec(det.boxes.tolist(), [(10, 11)]))
    assert c.wheels_correct == 0 and c.pair_fp == 1


def test_score_records_sums_and_missing_images_have_no_relations():
    other = rec(GT.boxes.tolist(), GT.relations, GT.wheel_pairs, image="b.png")
    total = score_records([GT, other], {"a.png": with_relations([(0, 1), (0, 2)], [(1, 2)])})
    assert (total.images, total.images_correct, total.wheels, total.wheels_correct) == (2, 1, 6, 4)
