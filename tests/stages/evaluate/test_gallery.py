"""Choosing and framing the gallery's disagreement images."""

import numpy as np

from deepword.word_format import Record
from stages.evaluate.gallery import disagreements, focus_region


def rec(image, relations, boxes=((10, 10, 50, 40, 1, 0, 0), (12, 30, 20, 40, 1, 1, 1))):
    return Record(image=image, frame_id=0, camera="left", width=100, height=80,
                  boxes=np.array(boxes, dtype=float), relations=[(v, w, None) for v, w in relations], wheel_pairs=[])


def test_disagreements_keep_images_where_methods_differ_most_wrong_first():
    gts = [rec("a", [(0, 1)]), rec("b", [(0, 1)]), rec("c", [(0, 1)])]
    preds = {"m1": {"a": rec("a", [(0, 1)]), "b": rec("b", []), "c": rec("c", [])},
             "m2": {"a": rec("a", [(0, 1)]), "b": rec("b", [(0, 1)]), "c": rec("c", [])}}
    # a: all agree (skipped); b: one wrong; c: both wrong but agreeing (skipped)
    assert [r.image for r in disagreements(gts, preds, limit=5)] == ["b"]
    assert disagreements(gts, preds, limit=0) == []


def test_disagreements_on_detected_boxes_rank_by_wrong_wheels_through_the_matching():
    # two vehicles, a wheel of each; the detections are shifted a little and numbered otherwise (ids 5..8)
    truth = ((10, 10, 50, 40, 1, 0, 0), (12, 30, 20, 40, 1, 1, 1), (55, 10, 95, 40, 1, 0, 2), (80, 30, 90, 40, 1, 1, 3))
    detected = ((11, 10, 50, 41, 0.9, 0, 5), (12, 31, 20, 40, 0.9, 1, 6), (55, 11, 95, 40, 0.9, 0, 7),
                (80, 30, 91, 40, 0.9, 1, 8))
    gts = [rec(name, [(0, 1), (2, 3)], truth) for name in ("a", "b")]
    preds = {"m1": {"a": rec("a", [(5, 6), (7, 8)], detected), "b": rec("b", [(5, 6), (7, 8)], detected)},
             "m2": {"a": rec("a", [(5, 6)], detected), "b": rec("b", [(7, 6), (5, 8)], detected)}}
    # the ids never equal the ground truth's, yet a is one wrong wheel (m2 misses wheel 3) and b two (m2 swaps)
    assert [r.image for r in disagreements(gts, preds, limit=5)] == ["b", "a"]


def test_focus_region_frames_the_boxes_with_a_margin_inside_the_image():
    assert focus_region(rec("a", []), margin=5) == (5, 5, 55, 45)
    assert focus_region(rec("a", []), margin=30) == (0, 0, 80, 70)
    empty = rec("e", [], boxes=np.zeros((0, 7)))
    assert focus_region(empty) == (0, 0, 100, 80)
