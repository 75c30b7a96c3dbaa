"""Choosing and framing the gallery's disagreement images."""

import numpy as np

from stages.evaluate.gallery import disagreements, focus_region
from stages.word_format import Record


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


def test_focus_region_frames_the_boxes_with_a_margin_inside_the_image():
    assert focus_region(rec("a", []), margin=5) == (5, 5, 55, 45)
    assert focus_region(rec("a", []), margin=30) == (0, 0, 80, 70)
    empty = rec("e", [], boxes=np.zeros((0, 7)))
    assert focus_region(empty) == (0, 0, 100, 80)
