"""Vehicles the ego's own body hides: where the calibration's ``ego_body`` covers the image just beyond a seen box's
edge, a no-wheel fit lets the vehicle reach beyond that edge unseen, and its confidence still counts the edge."""

import math
from dataclasses import replace

import numpy as np

from deepword.footprint import (
    _size,
    box_bottom_estimate,
    estimate_record,
    fit_free,
    fit_sized,
    fit_trust,
    hidden_edges,
    seen_cost,
    silhouette_boxes,
)
from deepword.format_3d import Box3D
from deepword.word_format import Record
from tests.stages.bev.test_bev import PRIOR, _camera

# cars beside the left camera (x, y, yaw): their image's lower third falls behind the ego's body
CARS = [(0.5, 4.0, 0.05), (2.0, 5.0, 0.0), (-1.0, 3.5, 0.2), (1.0, 6.0, 1.5), (3.0, 4.0, 0.3)]


def _hidden_bottom(cam, x, y, yaw):
    """The camera with an ego body over the image's bottom from a third of the car's image up, and the car's seen
    box, which ends on it."""
    whole = silhouette_boxes(cam, [[x, y]], [yaw], _size(PRIOR), PRIOR.shape)[0]
    edge = whole[3] - (whole[3] - whole[1]) / 3
    body = ((0.0, edge), (float(cam.width), edge), (float(cam.width), float(cam.height)), (0.0, float(cam.height)))
    return replace(cam, ego_body=(body,)), np.r_[whole[:3], edge, 1.0, 0, 0]


def test_only_the_edge_that_ends_on_the_ego_body_is_hidden():
    plain = _camera()
    cam, seen = _hidden_bottom(plain, *CARS[0])
    assert hidden_edges(plain, seen) is None
    assert hidden_edges(cam, seen).tolist() == [False, False, False, True]
    above = seen.copy()
    above[3] -= 20   # 20 px above the body: what lies below the box is seen, so the vehicle ends there
    assert not hidden_edges(cam, above).any()


def test_a_no_wheel_vehicle_whose_bottom_the_ego_body_hides_is_placed_by_its_other_edges():
    """Fitted as if it ended where it is hidden, each car stands 8-24 cm off (further, its image shrunk); with the
    edge free, within 5 cm."""
    plain_errors = []
    for x, y, yaw in CARS:
        cam, seen = _hidden_bottom(_camera(), x, y, yaw)
        fitted = fit_sized(fit_free, cam, seen, PRIOR, box_bottom_estimate(cam, seen, PRIOR), [yaw])[0]
        assert math.hypot(fitted.x - x, fitted.y - y) < 0.05, (x, y, yaw)
        plain = fit_sized(fit_free, _camera(), seen, PRIOR, box_bottom_estimate(cam, seen, PRIOR), [yaw])[0]
        plain_errors.append(math.hypot(plain.x - x, plain.y - y))
    assert min(plain_errors) > 0.05


def test_its_confidence_counts_the_hidden_edge():
    """The fit explains the box up to the ego body, but the part it puts behind the body is unseen: its confidence
    takes the trust of its cost with every edge counted, less than its search's cost alone would give."""
    x, y, yaw = CARS[2]
    cam, seen = _hidden_bottom(_camera(), x, y, yaw)
    rec = Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                 boxes=np.array([[*seen[:4], 0.9, 0, 0]]), relations=[], wheel_pairs=[])
    [est] = estimate_record(rec, cam, PRIOR)
    assert est.evidence == "box"
    box = Box3D(est.box.x, est.box.y, est.box.length, est.box.width, est.box.yaw)
    free = fit_sized(fit_free, cam, seen, PRIOR, box_bottom_estimate(cam, seen, PRIOR), None)[1]
    counted = seen_cost(cam, box, seen, PRIOR)
    assert counted > free
    assert est.confidence == 0.3 * 0.9 * fit_trust(counted) < 0.3 * 0.9 * fit_trust(free)
