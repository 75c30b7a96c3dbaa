import dataclasses
import math

import numpy as np
import pytest

from deepword.detection.ap_errors import ap_error_breakdown, append_breakdown, classify, error_metrics
from deepword.detection.average_precision import coco_average_precision
from deepword.word_format import Record


def record(boxes: list[tuple], image: str = "a.png") -> Record:
    """A 200 x 100 record of (x1, y1, x2, y2, score, class) boxes, box ids 0.."""
    arr = np.array([(*b, i) for i, b in enumerate(boxes)], dtype=np.float64).reshape(-1, 7)
    return Record(image=image, frame_id="f0", camera="front", width=200, height=100, boxes=arr, relations=[],
                  wheel_pairs=[])


TRUTH = record([(10, 10, 60, 60, 1, 0),       # vehicle A
                (100, 10, 160, 70, 1, 0),     # vehicle B, only ever found loosely
                (20, 50, 30, 60, 1, 1),       # a 10 px wheel
                (180, 90, 184, 94, 1, 1)])    # a 4 px wheel: ignored under min_box_px 8
DETECTIONS = record([(10, 10, 60, 61, 0.9, 0),    # finds A
                     (11, 10, 60, 60, 0.8, 0),    # A again: duplicate
                     (100, 10, 125, 40, 0.7, 0),  # a quarter of B: loose (IoU 0.21)
                     (0, 80, 8, 98, 0.95, 0),     # nothing there: background, the best score
                     (20, 50, 30, 61, 0.6, 1),    # finds the wheel
                     (179, 89, 184, 94, 0.5, 1)])  # on the ignored wheel: neither kind


def test_each_detection_gets_its_kind():
    errors = classify(TRUTH, DETECTIONS, min_box_px=8)
    assert errors.kind == ["tp", "duplicate", "loose", "background", "tp", "ignored"]
    assert errors.place_on[2] == 1 and (np.delete(errors.place_on, 2) == -1).all()
    assert errors.found == {0: 1, 1: 1} and errors.evaluated == {0: 2, 1: 1}


def test_a_detection_in_an_ignore_region_is_no_error():
    truth = dataclasses.replace(TRUTH, ignore=np.array([[0, 78, 10, 100, 0]], dtype=np.float64))  # a hidden vehicle
    assert classify(truth, DETECTIONS, min_box_px=8).kind[3] == "ignored"


def test_oracles_are_the_ap_of_a_detector_without_those_errors():
    out = ap_error_breakdown([TRUTH], [DETECTIONS], ("vehicle", "wheel"), min_box_px=8)
    vehicle = out["vehicle"]
    as_reported = coco_average_precision([DETECTIONS], [TRUTH], ("vehicle", "wheel"), 8)
    assert vehicle["ap50"] == pytest.approx(as_reported["vehicle"]["ap50"])
    assert vehicle["max_recall"] == 50.0 and out["wheel"]["max_recall"] == 100.0
    assert (vehicle["n_background"], vehicle["n_duplicate"], vehicle["n_loose"]) == (1, 1, 1)
    # the background box outscores everything: without it the first detection found is correct
    without_background = record([b[:6] for k, b in enumerate(DETECTIONS.boxes) if k != 3])
    assert vehicle["ap50_no_background"] == pytest.approx(
        coco_average_precision([without_background], [TRUTH], ("vehicle", "wheel"), 8)["vehicle"]["ap50"])
    assert vehicle["ap50_no_background"] > vehicle["ap50"]
    # placing the loose box on B finds every vehicle; without any false positive only A is ever found
    assert vehicle["ap50_loose_placed"] > vehicle["ap50"]
    assert vehicle["ap50_no_false_positives"] == pytest.approx(50.0, abs=0.6)   # 101-point precision at recall 0.5
    assert out["wheel"]["ap50_no_false_positives"] == pytest.approx(out["wheel"]["ap50"]) == pytest.approx(100.0)


def test_metrics_and_report(tmp_path):
    out = ap_error_breakdown([TRUTH], [DETECTIONS], ("vehicle", "wheel"), min_box_px=8)
    metrics = error_metrics(out, "test")
    assert metrics["detector.test.max_recall.vehicle"] == 50.0
    assert {"detector.test.ap50_loose_placed.wheel", "detector.test.ap50_no_duplicates.vehicle"} <= set(metrics)
    assert not any(".n_" in k for k in metrics)
    report = tmp_path / "misses.md"
    report.write_text("# What the detector misses\n")
    append_breakdown(report, out, "test split", 8)
    text = report.read_text()
    assert text.startswith("# What the detector misses\n") and "## Where AP@0.5 goes (test split)" in text
    assert "| ground truth found at any score (max recall) | 50.0 % | – | 100.0 % | – |" in text


def test_mismatched_images_are_an_error():
    with pytest.raises(ValueError, match="b.png"):
        ap_error_breakdown([TRUTH], [record([], image="b.png")], ("vehicle", "wheel"), 8)


def test_class_without_ground_truth():
    out = ap_error_breakdown([record([(10, 10, 60, 60, 1, 0)])], [record([(10, 10, 60, 60, 0.9, 0)])],
                             ("vehicle", "wheel"), 8)
    assert out["vehicle"]["ap50"] == pytest.approx(100.0)
    assert math.isnan(out["wheel"]["max_recall"])
