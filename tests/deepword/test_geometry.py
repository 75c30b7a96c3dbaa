"""Eq. 1-2, IoU and containment against values computed by hand."""

import math

import numpy as np
import pytest

from deepword import geometry as g


def test_box_centres():
    assert g.box_centres(np.array([[0, 0, 10, 20], [2, 4, 6, 8]])).tolist() == [[5, 10], [4, 6]]


def test_normalised_distance_by_hand():
    # centres (10, 10) and (40, 50) in a 100 x 200 image: dx = 0.3, dy = 0.2 -> D = sqrt(0.13)
    a = np.array([0, 0, 20, 20])
    b = np.array([30, 40, 50, 60])
    assert g.normalised_distance(a, b, 100, 200) == pytest.approx(math.sqrt(0.13))


def test_distance_ratio_by_hand():
    # same pair: B is 20 x 20 -> size = 20/100 + 20/200 = 0.3; ratio = 2 sqrt(0.13) / 0.3
    a = np.array([0, 0, 20, 20])
    b = np.array([30, 40, 50, 60])
    assert g.distance_ratio(a, b, 100, 200) == pytest.approx(2 * math.sqrt(0.13) / 0.3)


def test_distance_ratio_uses_b_size_only():
    a = np.array([0, 0, 20, 20])
    b = np.array([30, 40, 50, 60])
    bigger_a = np.array([-10, -10, 30, 30])  # same centre, different size: ratio unchanged
    assert g.distance_ratio(bigger_a, b, 100, 200) == pytest.approx(g.distance_ratio(a, b, 100, 200))
    assert g.distance_ratio(b, a, 100, 200) == pytest.approx(g.distance_ratio(a, b, 100, 200))  # equal sizes


def test_pairwise_distance_ratio_matches_elementwise():
    a = np.array([[0, 0, 20, 20], [50, 50, 90, 70]], dtype=float)
    b = np.array([[30, 40, 50, 60], [10, 10, 14, 18], [0, 100, 8, 110]], dtype=float)
    r = g.pairwise_distance_ratio(a, b, 128, 96)
    assert r.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            assert r[i, j] == pytest.approx(g.distance_ratio(a[i], b[j], 128, 96))


def test_iou_by_hand():
    a = np.array([[0, 0, 10, 10]])
    b = np.array([[5, 5, 15, 15], [0, 0, 10, 10], [20, 20, 30, 30], [10, 0, 20, 10]])
    # overlap 5x5 = 25, union 100 + 100 - 25 = 175; identical -> 1; disjoint -> 0; touching edge -> 0
    np.testing.assert_allclose(g.pairwise_iou(a, b), [[25 / 175, 1.0, 0.0, 0.0]])


def test_intersection_and_containment_by_hand():
    wheel = np.array([[8, 8, 12, 12]])  # area 16
    vehicles = np.array([[0, 0, 10, 10], [0, 0, 20, 20], [30, 30, 40, 40]])
    np.testing.assert_allclose(g.pairwise_intersection(wheel, vehicles), [[4, 16, 0]])
    np.testing.assert_allclose(g.containment(wheel, vehicles), [[0.25, 1.0, 0.0]])


def test_empty_inputs_give_empty_matrices():
    none = np.zeros((0, 4))
    some = np.array([[0, 0, 1, 1]])
    assert g.pairwise_iou(none, some).shape == (0, 1)
    assert g.containment(some, none).shape == (1, 0)
    assert g.pairwise_distance_ratio(none, some, 10, 10).shape == (0, 1)
