"""The wheels' roles scored apart from the §7 metrics: judged on the true relations found whose role is labelled."""

from dataclasses import replace

import pytest

from deepword.scoring.roles import role_scores, true_roles
from tests.deepword.test_metrics import GT, rec


def test_roles_are_judged_on_the_true_relations_found_whose_role_is_labelled():
    gt = rec(GT.boxes.tolist(), [(0, 1, "rear"), (0, 2, None)], [(1, 2)])
    # boxes shifted by a pixel and renumbered: matched by IoU; the wheel without a true role is not judged
    shifted = [[b[0] + 1, b[1], b[2] + 1, b[3], 0.9, b[5], 10 + b[6]] for b in GT.boxes.tolist()]
    right = rec(shifted, [(10, 11, "rear"), (10, 12, "front")])
    assert true_roles(gt, right) == {(10, 11): "rear"}
    wrong = rec(shifted, [(10, 11, "front"), (10, 13, "rear")])   # a wrong role; a relation that is not true
    unnamed = rec(shifted, [(10, 11, None)])
    scores = role_scores([gt, replace(gt, image="b.png"), replace(gt, image="c.png")],
                         {"a.png": right, "b.png": replace(wrong, image="b.png"), "c.png": replace(unnamed, image="c.png")})
    assert scores == {"role_acc": pytest.approx(100 / 3), "relations": 3.0, "without_role": 1.0}
    assert role_scores([GT], {"a.png": GT}) == {"role_acc": 100.0, "relations": 0.0, "without_role": 0.0}
