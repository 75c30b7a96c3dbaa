"""``deepword_then_logic``: the first method's claims stay as they are; the second only adds owners of wheels the
first left unclaimed, so no wheel ever has two owners."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from deepword.rules.fallback import ClaimFallback
from deepword.word_format import Record, boxes_only
from stages.evaluate.methods import METHODS

# vehicles 0 and 1, wheels 2, 3 and 4 (x1, y1, x2, y2, score, class, id; class 0 vehicle, 1 wheel)
BOXES = np.array([[0, 0, 100, 60, 1, 0, 0], [120, 0, 200, 60, 1, 0, 1], [10, 40, 30, 60, 1, 1, 2],
                  [70, 40, 90, 60, 1, 1, 3], [130, 40, 150, 60, 1, 1, 4]], np.float32)
RECORD = Record(image="f.png", frame_id=0, camera="left", width=200, height=100, boxes=BOXES, relations=[],
                wheel_pairs=[])


class Fixed:
    """A method that always predicts the given relations and couples."""

    def __init__(self, relations, wheel_pairs=()):
        self.relations, self.wheel_pairs = relations, list(wheel_pairs)

    def predict(self, rec: Record) -> Record:
        return replace(boxes_only(rec), relations=list(self.relations), wheel_pairs=list(self.wheel_pairs))


def test_the_fallback_claims_only_the_wheels_the_first_method_left_unclaimed():
    first = Fixed([(0, 2, "rear"), (0, 3, "front")], wheel_pairs=[(2, 3)])
    # the rule disagrees on wheel 3 (vehicle 1), agrees on 2 and claims wheel 4, which the first method left alone
    rule = Fixed([(0, 2, None), (1, 3, None), (1, 4, None)])
    pred = ClaimFallback(first, rule, "first_then_rule").predict(RECORD)
    assert pred.relations == [(0, 2, "rear"), (0, 3, "front"), (1, 4, None)]
    assert pred.wheel_pairs == [(2, 3)]  # couples are the first method's
    owners = [w for _, w, _ in pred.relations]
    assert len(owners) == len(set(owners))
    np.testing.assert_array_equal(pred.boxes, RECORD.boxes)


def test_a_fallback_with_nothing_to_add_changes_nothing():
    first = Fixed([(0, 2, "rear"), (1, 4, "rear")])
    mine = [(0, 2, "rear"), (1, 4, "rear")]
    assert ClaimFallback(first, Fixed([]), "first_then_none").predict(RECORD).relations == mine
    assert ClaimFallback(Fixed([]), first, "none_then_first").predict(RECORD).relations == mine


def test_the_row_is_registered_and_in_the_default_report():
    from pathlib import Path

    from omegaconf import OmegaConf

    assert "deepword_then_logic" in METHODS
    conf = OmegaConf.load(Path(__file__).parents[3] / "conf" / "eval" / "default.yaml")
    assert "deepword_then_logic" in conf.methods


def test_a_batch_predictor_with_a_fallback_adds_the_same_claims_as_the_row():
    """What the operating-point search scores (a batch predictor with the fallback) is what the row predicts."""
    from deepword.rules.fallback import batch_with_fallback

    first = Fixed([(0, 2, "rear")])
    rule = Fixed([(1, 2, None), (1, 4, None)])
    calls = []

    def batch(records):
        calls.append(len(records))
        return [first.predict(r) for r in records]

    other = replace(RECORD, image="g.png")
    preds = batch_with_fallback(batch, rule)([RECORD, other])
    assert calls == [2]  # the primary still sees the whole batch at once
    row = ClaimFallback(first, rule, "first_then_rule")
    assert [p.relations for p in preds] == [row.predict(RECORD).relations, row.predict(other).relations]
    assert preds[0].relations == [(0, 2, "rear"), (1, 4, None)]

