import dataclasses
import math

import numpy as np
import pytest

from deepword.detection.average_precision import coco_average_precision
from deepword.word_format import Record


def rec(name: str, boxes: list[list[float]]) -> Record:
    return Record(image=name, frame_id=0, camera="front", width=100, height=100,
                  boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7), relations=[], wheel_pairs=[])


def test_perfect_detections_score_100():
    gt = [rec("a", [[0, 0, 50, 50, 1, 0, 0], [60, 60, 70, 70, 1, 1, 1]]), rec("b", [[10, 10, 30, 30, 1, 1, 0]])]
    ap = coco_average_precision(gt, gt)
    assert set(ap) == {"vehicle", "wheel"}
    for per_class in ap.values():
        assert per_class == {"ap50": pytest.approx(100.0), "ap": pytest.approx(100.0)}


def test_iou_062_counts_at_three_of_ten_thresholds():
    gt = [rec("a", [[0, 0, 10, 10, 1, 1, 0]])]
    pred = [rec("a", [[0, 0, 10, 6.2, 0.9, 1, 0]])]  # IoU 0.62 >= 0.50, 0.55, 0.60 only
    ap = coco_average_precision(pred, gt)["wheel"]
    assert ap["ap50"] == pytest.approx(100.0) and ap["ap"] == pytest.approx(30.0)


def test_ranking_matters_and_missing_classes():
    gt = [rec("a", [[0, 0, 10, 10, 1, 1, 0]])]
    # a confident false positive ranked above the true positive halves the precision at full recall
    pred = [rec("a", [[50, 50, 60, 60, 0.9, 1, 0], [0, 0, 10, 10, 0.5, 1, 1]])]
    assert coco_average_precision(pred, gt)["wheel"]["ap50"] == pytest.approx(50.0, abs=1.0)
    assert math.isnan(coco_average_precision(pred, gt)["vehicle"]["ap"])  # no vehicle in the ground truth
    empty = [dataclasses.replace(gt[0], boxes=np.zeros((0, 7)))]
    assert coco_average_precision(empty, gt)["wheel"]["ap50"] == 0.0
    with pytest.raises(ValueError, match="ground truth"):
        coco_average_precision([rec("b", [])], gt)


def test_boxes_below_min_box_px_are_ignored_not_missed_nor_false_positives():
    # a 5 px wheel missed and a 4 px wheel detected (ranked first), beside a 20 px wheel found
    gt = [rec("a", [[0, 0, 20, 20, 1, 1, 0], [50, 50, 55, 55, 1, 1, 1], [80, 80, 84, 84, 1, 1, 2]])]
    pred = [rec("a", [[80, 80, 84, 84, 0.9, 1, 0], [0, 0, 20, 20, 0.8, 1, 1]])]
    every_box = coco_average_precision(pred, gt)["wheel"]["ap50"]
    assert every_box == pytest.approx(66.7, abs=1.0)  # recall 2/3 at precision 1
    assert coco_average_precision(pred, gt, min_box_px=8)["wheel"]["ap50"] == pytest.approx(100.0)
    # only ground truth is ignored: a small false positive still counts against the detector
    fp = [rec("a", [[30, 30, 34, 34, 0.9, 1, 0], [0, 0, 20, 20, 0.8, 1, 1]])]
    assert coco_average_precision(fp, gt, min_box_px=8)["wheel"]["ap50"] == pytest.approx(50.0, abs=1.0)


def test_a_detection_in_an_ignore_region_is_neither_true_nor_false():
    gt = [rec("a", [[0, 0, 20, 20, 1, 1, 0]])]
    gt[0].ignore = np.array([[50, 50, 60, 58, 1]], dtype=np.float64)  # a wheel too hidden to label
    pred = [rec("a", [[50, 50, 60, 59, 0.9, 1, 0], [0, 0, 20, 20, 0.8, 1, 1]])]
    assert coco_average_precision(pred, gt)["wheel"]["ap50"] == pytest.approx(100.0)
    bare = [dataclasses.replace(gt[0], ignore=np.zeros((0, 5)))]
    assert coco_average_precision(pred, bare)["wheel"]["ap50"] == pytest.approx(50.0, abs=1.0)


def test_stage_reports_every_box_ap_beside_the_protocol_ap():
    from stages.detector.stage import ap_metrics

    gt = [rec("a", [[0, 0, 40, 40, 1, 0, 0], [0, 0, 20, 20, 1, 1, 1], [50, 50, 55, 55, 1, 1, 2]])]
    pred = [rec("a", [[0, 0, 40, 40, 0.9, 0, 0], [0, 0, 20, 20, 0.8, 1, 1]])]
    every_box = ap_metrics(pred, gt, "test", 0)
    assert set(every_box) == {f"detector.test.{k}.{c}" for k in ("ap50", "ap") for c in ("vehicle", "wheel")}
    both = ap_metrics(pred, gt, "test", 8)
    assert both["detector.test.ap50.wheel"] == pytest.approx(100.0)
    assert both["detector.test.ap50_all.wheel"] == pytest.approx(every_box["detector.test.ap50.wheel"])
    assert both["detector.test.ap50_all.wheel"] == pytest.approx(50.0, abs=1.0)
