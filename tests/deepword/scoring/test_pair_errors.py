"""Pair errors by cause (deepword/scoring/pair_errors.py) on hand-made cases, against the §7 counts."""

import numpy as np

from deepword.metrics import score_image, score_records
from deepword.scoring.pair_errors import PairErrors, pair_errors, pair_errors_records, relation_oracle
from tests.deepword.test_metrics import GT, rec


def test_pair_errors_name_one_cause_each_and_add_up_to_the_counts():
    # two vehicles 0 (wheels 1, 2) and 4 (wheel 5); detections: vehicle 0, its wheel 1, vehicle 4 and its wheel 5,
    # wheel 2 missed, a wheel box where no wheel is, a vehicle box where no vehicle is
    gt = rec([[0, 0, 100, 50, 1, 0, 0], [5, 30, 25, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2],
              [110, 0, 190, 50, 1, 0, 4], [160, 30, 180, 50, 1, 1, 5], [115, 30, 135, 50, 1, 1, 6]],
             relations=[(0, 1), (0, 2), (4, 5), (4, 6)])
    det = rec([[1, 0, 100, 51, 0.9, 0, 10], [5, 31, 25, 50, 0.9, 1, 11],       # vehicle 0, wheel 1
               [111, 0, 190, 50, 0.9, 0, 12], [160, 30, 181, 50, 0.9, 1, 13],  # vehicle 4, wheel 5
               [115, 30, 135, 50, 0.9, 1, 14],                                 # wheel 6
               [40, 5, 50, 15, 0.8, 1, 15],                                    # a wheel box on vehicle 0's roof
               [0, 60, 60, 99, 0.8, 0, 16]])                                   # a vehicle box on the road
    pred = rec(det.boxes.tolist(), [(10, 11), (10, 15), (16, 13), (10, 14)])
    e = pair_errors(gt, pred)
    # found (0, 1); missed (0, 2): wheel 2 not detected; (4, 5): claimed by the false vehicle, so both detected and
    # not paired; (4, 6): given to vehicle 0, both detected, not paired. False: wheel 15 matches no wheel, vehicle 16
    # matches no vehicle, (0, 6) is a wrong pair of real boxes
    assert e == PairErrors(found=1, wheel_missed=1, vehicle_missed=0, not_paired=2, false_wheel=1, false_vehicle=1,
                           wrong_pair=1)
    c = score_image(gt, pred)
    assert e.found == c.pair_tp
    assert e.wheel_missed + e.vehicle_missed + e.not_paired == c.pair_fn
    assert e.false_wheel + e.false_vehicle + e.wrong_pair == c.pair_fp


def test_pair_errors_vehicle_missed_duplicates_and_ignored_wheels():
    small = rec([[0, 0, 100, 50, 1, 0, 0], [5, 30, 25, 50, 1, 1, 1], [80, 45, 84, 50, 1, 1, 2]],
                relations=[(0, 1), (0, 2)])
    only_wheels = rec([[5, 30, 25, 50, 0.9, 1, 1], [80, 45, 84, 50, 0.9, 1, 2]])
    assert pair_errors(small, only_wheels, min_box_px=8) == PairErrors(vehicle_missed=1)  # wheel 2 not evaluated
    twice = rec(small.boxes.tolist(), [(0, 1), (0, 1), (0, 2)])  # a repeated true claim; a claim of a small wheel
    e = pair_errors(small, twice, min_box_px=8)
    assert e == PairErrors(found=1, wrong_pair=1)
    assert e.wrong_pair == score_image(small, twice, min_box_px=8).pair_fp


def test_pair_errors_records_sum_images_and_count_missing_ones_as_unclaimed():
    other = rec(GT.boxes.tolist(), [(0, 1), (0, 2)], image="b.png")
    gts = [GT, other]
    total = pair_errors_records(gts, {"b.png": other})
    assert total == PairErrors(found=2, not_paired=2)  # a.png has no prediction: its boxes, no claims
    assert total.as_dict()["not_paired"] == 2


def test_relation_oracle_claims_the_truth_on_found_boxes_and_nothing_else():
    # ground truth: vehicle 0 with wheels 1, 2 (a couple); vehicle 4 with wheel 5. Detections: vehicle 0 shifted by
    # a pixel, wheel 1, a loose box on wheel 2 (IoU < 0.5), vehicle 4 and wheel 5, a wheel box where no wheel is
    gt = rec([[0, 0, 100, 50, 1, 0, 0], [5, 30, 25, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2],
              [110, 0, 190, 50, 1, 0, 4], [160, 30, 180, 50, 1, 1, 5]],
             relations=[(0, 1), (0, 2), (4, 5)], pairs=[(1, 2)])
    det = rec([[1, 0, 101, 50, 0.9, 0, 10], [5, 30, 25, 50, 0.8, 1, 11], [85, 40, 99, 50, 0.7, 1, 12],
               [110, 0, 190, 50, 0.9, 0, 13], [160, 30, 180, 50, 0.9, 1, 14], [40, 5, 50, 15, 0.6, 1, 15]])
    oracle = relation_oracle(gt, det)
    # every true relation whose two boxes were found, in the detections' ids; the loose wheel and the false one
    # claim nothing, and the couple needs its loose wheel
    assert sorted((v, w) for v, w, _ in oracle.relations) == [(10, 11), (13, 14)]
    assert oracle.wheel_pairs == []
    assert oracle.boxes.tolist() == det.boxes.tolist() and det.relations == []  # boxes kept, input untouched
    c = score_image(gt, oracle)
    assert (c.pair_tp, c.pair_fp, c.pair_fn) == (2, 0, 1)  # never a false claim; misses are the detector's
    assert pair_errors(gt, oracle) == PairErrors(found=2, wheel_missed=1)
    # on the ground truth's own boxes it is the ground truth: every metric 100
    assert all(v == 100.0 for v in score_records([gt], {gt.image: relation_oracle(gt, gt)}).percentages().values())


def test_claims_in_ignore_regions_are_no_error():
    gt = rec(GT.boxes[:3].tolist(), relations=[(0, 1), (0, 2)])
    gt.ignore = np.array([[150, 40, 160, 50, 1]], dtype=np.float64)  # a wheel too hidden to label
    pred = rec(GT.boxes[:3].tolist() + [[150, 41, 160, 50, 0.5, 1, 9], [40, 5, 50, 15, 0.5, 1, 8]],
               [(0, 1), (0, 2), (0, 9), (0, 8)])
    e = pair_errors(gt, pred)
    assert e == PairErrors(found=2, false_wheel=1)  # the box on the roof is still false, the hidden wheel is not
    assert e.false_wheel == score_image(gt, pred).pair_fp
