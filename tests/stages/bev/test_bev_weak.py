"""Footprints of vehicles with one visible wheel or none: the wheel's role puts the centre on the right side of
it, the vehicle box's image fixes the heading and the position, a box bottom back-projects to its ground point,
neighbours lend their axis, and fusion keeps the better evidence."""

import math

import numpy as np
import pytest

from deepword.footprint import (
    ROLE_COUPLE_LOGIT,
    ROLE_WHEEL_LOGIT,
    Estimate,
    box_bottom_points,
    context_axes,
    estimate_frame,
    fit_free,
    fit_wheel,
    fuse_frame,
    silhouette_boxes,
)
from deepword.format_3d import Box3D
from deepword.word_format import Record
from tests.stages.bev.test_bev import PRIOR, _camera, _contacts


def _seen_box(cam, v: Box3D) -> np.ndarray:
    """The vehicle box the camera would see of ``v`` (the prior's size and silhouette model), with score 1."""
    return np.r_[silhouette_boxes(cam, [[v.x, v.y]], [v.yaw], (PRIOR.length, PRIOR.width, PRIOR.height),
                                  PRIOR.shape)[0], 1.0, 0, 0]


def _yaw_err(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, 2 * math.pi)))


@pytest.mark.parametrize("role, corner", [("rear", "rr"), ("front", "fr")])
def test_one_wheel_role_puts_the_centre_on_the_right_side(role, corner):
    cam = _camera()  # the left camera: sees the cars' right sides
    v = Box3D(2.2, 5.0, PRIOR.length, PRIOR.width, 0.1)
    contact = _contacts(v)[corner]
    box, _ = fit_wheel(cam, contact, role, _seen_box(cam, v), PRIOR)
    assert math.hypot(box.x - v.x, box.y - v.y) < 0.15
    assert _yaw_err(box.yaw, v.yaw) < 5     # over 360 deg: the heading points to the front
    ahead = float(np.dot(np.array([box.x, box.y]) - contact, (math.cos(v.yaw), math.sin(v.yaw))))
    assert (ahead > 0) == (role == "rear")  # the centre lies ahead of a rear wheel, behind a front one


def test_one_wheel_with_a_neighbours_axis():
    cam = _camera()
    v = Box3D(-1.5, 5.5, PRIOR.length, PRIOR.width, math.pi / 2)   # nose-in, seen end-on
    contact = _contacts(v)["rl"]
    box, _ = fit_wheel(cam, contact, "rear", _seen_box(cam, v), PRIOR, axes=[-math.pi / 2])
    assert math.hypot(box.x - v.x, box.y - v.y) < 0.05 and _yaw_err(box.yaw, v.yaw) < 1


def test_a_box_bottom_back_projects_to_its_ground_point():
    cam = _camera()
    ground = np.array([cam.translation[0], cam.translation[1] + 3.0, 0.0])   # 3 m straight out of the left camera
    uv, _ = cam.project(ground[None])
    u, v = uv[0]
    box = np.array([[u - 20 + 0.5, v - 40 + 0.5, u + 20 + 0.5, v + 0.5]])     # box coordinates: image + 0.5
    xy, ok = box_bottom_points(cam, box)
    assert ok[0] and np.allclose(xy[0], ground[:2], atol=0.02)


@pytest.mark.parametrize("turn", [0.0, math.pi])
def test_no_wheel_vehicle_end_on_is_found_from_its_box(turn):
    cam = _camera()
    x, y = 1.2, 6.0   # its axis along the camera's view of it, nose away (turn 0) or towards the camera
    v = Box3D(x, y, PRIOR.length, PRIOR.width, math.atan2(y - cam.translation[1], x - cam.translation[0]) + turn)
    start = Box3D(v.x + 0.8, v.y - 0.9, PRIOR.length, PRIOR.width, 0.0)  # a poor first guess
    box, cost = fit_free(cam, _seen_box(cam, v), PRIOR, start)
    assert math.hypot(box.x - v.x, box.y - v.y) < 0.2
    assert abs(math.degrees(math.remainder(box.yaw - v.yaw, math.pi))) < 5 and cost < 1e-3


def test_no_wheel_vehicle_takes_its_neighbours_axis():
    cam = _camera()
    v = Box3D(3.0, 5.5, PRIOR.length, PRIOR.width, 1.3)  # angled bay: not end-on to the camera
    neighbour = Box3D(0.5, 5.3, PRIOR.length, PRIOR.width, 1.3 + math.pi)
    axes = context_axes([neighbour], (v.x, v.y))
    assert axes == [neighbour.yaw]
    start = Box3D(v.x - 0.6, v.y + 0.7, PRIOR.length, PRIOR.width, 0.0)
    box, _ = fit_free(cam, _seen_box(cam, v), PRIOR, start, axes)
    assert math.hypot(box.x - v.x, box.y - v.y) < 0.1
    assert abs(math.degrees(math.remainder(box.yaw - v.yaw, math.pi))) < 1e-6
    assert context_axes([neighbour], (v.x + 20, v.y)) == []   # too far to be its neighbour


def test_estimate_frame_lends_a_side_footprints_axis_to_a_one_wheel_vehicle():
    cam = _camera()
    a = Box3D(-1.5, 5.6, PRIOR.length, PRIOR.width, math.pi / 2)    # one wheel seen (its rear left), end-on
    b = Box3D(1.5, 5.6, PRIOR.length, PRIOR.width, math.pi / 2)     # its neighbour: both right wheels seen
    ca, cb = _contacts(a), _contacts(b)
    boxes = [[*_seen_box(cam, a)[:4], 1.0, 0, 0], [*_seen_box(cam, b)[:4], 1.0, 0, 1],
             [10, 10, 20, 20, 1.0, 1, 2], [30, 10, 40, 20, 1.0, 1, 3], [50, 10, 60, 20, 1.0, 1, 4]]
    rec = Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                 boxes=np.array(boxes), relations=[(0, 2, "rear"), (1, 3, "rear"), (1, 4, "front")],
                 wheel_pairs=[(3, 4)])
    contacts = {2: ca["rl"], 3: cb["rr"], 4: cb["fr"]}

    est = estimate_frame([(rec, cam)], PRIOR, contacts=[contacts])
    one = next(e for e in est if e.vehicle_box_id == 0)
    assert one.evidence == "wheel" and one.directed
    assert math.hypot(one.box.x - a.x, one.box.y - a.y) < 0.1 and _yaw_err(one.box.yaw, a.yaw) < 1


def test_fusion_keeps_the_better_evidence():
    truth = Box3D(2.0, 5.0, 4.5, 1.8, 0.1)
    side = Estimate(box=truth, evidence="side", camera="left", vehicle_box_id=0, image="l.png", confidence=0.9,
                    role_vote=ROLE_COUPLE_LOGIT)
    off = Box3D(truth.x + 0.6, truth.y + 0.4, 4.5, 1.8, 0.5)
    wheel = Estimate(box=off, evidence="wheel", camera="front", vehicle_box_id=3, image="f.png", confidence=0.5,
                     role_vote=ROLE_WHEEL_LOGIT)
    bare = Estimate(box=Box3D(truth.x - 0.7, truth.y, 4.5, 1.8, 1.2), evidence="box", camera="rear",
                    vehicle_box_id=1, image="r.png", confidence=0.3)
    for order in ([wheel, side, bare], [bare, wheel, side]):
        fused = fuse_frame(order, radius_m=1.5)
        assert len(fused) == 1
        box, group = fused[0]
        assert group[0].evidence == "side" and box == truth and max(e.confidence for e in group) == 0.9
