"""Candidate pairs and their labels for the priors."""

import numpy as np
import pytest

from deepword.geometry import distance_ratio
from deepword.word_format import Record
from stages.priors.pairs import collect_ratios, record_ratios


def test_record_ratios_labels_and_counts():
    boxes = np.array([[0, 0, 100, 50, 1, 0, 0], [120, 0, 200, 50, 1, 0, 5],
                      [5, 30, 25, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2], [150, 30, 170, 50, 1, 1, 3]], float)
    rec = Record(image="a.png", frame_id=0, camera="left", width=200, height=100, boxes=boxes,
                 relations=[(0, 1, "rear"), (0, 2, "front"), (5, 3, None)], wheel_pairs=[(1, 2)])
    r = record_ratios(rec)
    wv, ww = r["wheel_vehicle"], r["wheel_wheel"]
    assert len(wv.pairs) == 3 and len(wv.non_pairs) == 3  # 2 vehicles x 3 wheels
    # wheel-wheel: 6 ordered pairs; 1 couple (rear 1 -> front 2), its reverse dropped, 4 non-pairs
    assert len(ww.pairs) == 1 and len(ww.non_pairs) == 4
    assert ww.pairs[0] == pytest.approx(distance_ratio(boxes[2, :4], boxes[3, :4], 200, 100))
    assert sorted(wv.pairs) == pytest.approx(sorted(
        [distance_ratio(boxes[v, :4], boxes[w, :4], 200, 100) for v, w in [(0, 2), (0, 3), (1, 4)]]))


def test_collect_ratios_handles_empty_records():
    empty = Record(image="e.png", frame_id=1, camera="left", width=10, height=10, boxes=np.zeros((0, 7)),
                   relations=[], wheel_pairs=[])
    out = collect_ratios([empty])
    assert all(len(v.pairs) == 0 and len(v.non_pairs) == 0 for v in out.values())
