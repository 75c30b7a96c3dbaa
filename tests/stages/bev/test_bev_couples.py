"""What a frame's couples and vehicle boxes say beyond each vehicle's own wheels: a couple no vehicle box owns is a
side of a vehicle the detector missed, a couple shorter than any wheelbase is no side, a couple far longer than the
prior's whose footprint overshoots its vehicle box is no side either (a bus's, which fits its box, is), and two
vehicle boxes of one image are two vehicles however close their estimates lie."""

import math

import numpy as np
import pytest

from deepword.footprint import (
    EVIDENCE_CONFIDENCE,
    MIN_COUPLE_SHARE,
    ORPHAN_CONFIDENCE,
    SIDE_FIT_MAX_COST,
    SIDE_LENGTH_BAND,
    Estimate,
    _side_box,
    _size,
    estimate_frame,
    fuse_frame,
    plausible_wheels,
    side_fits_box,
    silhouette_boxes,
    silhouette_cost,
)
from deepword.format_3d import Box3D
from deepword.word_format import Record
from tests.stages.bev.test_bev import PRIOR, _camera, _contacts
from tests.stages.bev.test_bev_long import _seen
from tests.stages.bev.test_bev_weak import _seen_box


def _wheels_only(cam, scores=(0.8, 0.6)) -> Record:
    """Two wheel boxes (ids 0, 1) paired as a couple, no vehicle box, no owner."""
    boxes = [[10, 10, 20, 20, scores[0], 1, 0], [30, 10, 40, 20, scores[1], 1, 1]]
    return Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                  boxes=np.array(boxes, dtype=float), relations=[], wheel_pairs=[(0, 1)])


def test_a_couple_no_vehicle_box_owns_is_a_side_of_its_own():
    cam = _camera()   # the left camera: sees the right sides of vehicles on the left
    v = Box3D(1.0, 5.5, PRIOR.length, PRIOR.width, 0.05)
    c = _contacts(v)
    est = estimate_frame([(_wheels_only(cam), cam)], PRIOR, contacts=[{0: c["rr"], 1: c["fr"]}])
    assert len(est) == 1
    e = est[0]
    assert e.evidence == "side" and e.vehicle_box_id is None
    assert math.hypot(e.box.x - v.x, e.box.y - v.y) < 0.05
    assert abs(math.degrees(math.remainder(e.box.yaw - v.yaw, math.pi))) < 0.5
    assert e.confidence == pytest.approx(EVIDENCE_CONFIDENCE["side"] * ORPHAN_CONFIDENCE * 0.7)
    assert e.box.height == PRIOR.height   # a box of the prior's height, as a vehicle box's side estimate


def test_a_couple_with_an_owned_wheel_gives_no_orphan():
    cam = _camera()
    v = Box3D(1.0, 5.5, PRIOR.length, PRIOR.width, 0.05)
    c = _contacts(v)
    rec = _wheels_only(cam)
    vehicle = [*_seen_box(cam, v)[:4], 0.9, 0, 2]
    rec = Record(image=rec.image, frame_id=0, camera="left", width=cam.width, height=cam.height,
                 boxes=np.vstack([rec.boxes, vehicle]), relations=[(2, 0, None)], wheel_pairs=[(0, 1)])
    est = estimate_frame([(rec, cam)], PRIOR, contacts=[{0: c["rr"], 1: c["fr"]}])
    assert [e.vehicle_box_id for e in est] == [2]   # the vehicle's one-wheel estimate, nothing else
    assert est[0].evidence == "wheel"


def test_a_couple_shorter_than_any_wheelbase_is_no_side():
    cam = _camera()
    v = Box3D(1.0, 5.5, PRIOR.length, PRIOR.width, 0.05)
    c = _contacts(v)
    twice = c["rr"] + np.array([0.0, 0.3])   # one wheel boxed twice: a "couple" 0.3 m long
    vehicle = [*_seen_box(cam, v)[:4], 0.9, 0, 2]
    rec = Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                 boxes=np.array([[10, 10, 20, 20, 0.8, 1, 0], [12, 10, 22, 20, 0.6, 1, 1], vehicle], dtype=float),
                 relations=[(2, 0, None), (2, 1, None)], wheel_pairs=[(0, 1)])
    contacts = {0: c["rr"], 1: twice}
    kept = plausible_wheels(rec, contacts, PRIOR)
    assert kept.wheel_pairs == [] and kept.relations == [(2, 0, None)]   # the weaker box (score 0.6) leaves
    assert len(kept.boxes) == 3                                          # its box stays
    est = estimate_frame([(rec, cam)], PRIOR, contacts=[contacts])
    assert [e.evidence for e in est] == ["wheel"]
    assert math.hypot(est[0].box.x - v.x, est[0].box.y - v.y) < 0.3

    # a real couple, one wheelbase long, is kept as it is
    whole = Record(image=rec.image, frame_id=0, camera="left", width=cam.width, height=cam.height, boxes=rec.boxes,
                   relations=rec.relations, wheel_pairs=[(0, 1)])
    assert plausible_wheels(whole, {0: c["rr"], 1: c["fr"]}, PRIOR) is whole
    # the threshold is a share of the prior's wheelbase: just above it is a side, just below it is not
    step = np.array([MIN_COUPLE_SHARE * PRIOR.wheelbase, 0.0])
    assert plausible_wheels(whole, {0: c["rr"], 1: c["rr"] + step * 1.01}, PRIOR) is whole
    assert plausible_wheels(whole, {0: c["rr"], 1: c["rr"] + step * 0.99}, PRIOR).wheel_pairs == []


def test_a_couple_spanning_two_vehicles_is_no_side_of_the_box_that_owns_it():
    cam = _camera()
    car = Box3D(1.0, 5.5, PRIOR.length, PRIOR.width, 0.0)
    ahead = _contacts(Box3D(6.5, 5.5, PRIOR.length, PRIOR.width, 0.0))   # the next car of the row, 1 m ahead
    vehicle = [*_seen_box(cam, car)[:4], 0.9, 0, 2]
    rec = Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                 boxes=np.array([[10, 10, 20, 20, 0.8, 1, 0], [30, 10, 40, 20, 0.7, 1, 1], vehicle], dtype=float),
                 relations=[(2, 0, None), (2, 1, None)], wheel_pairs=[(0, 1)])
    contacts = {0: _contacts(car)["rr"], 1: ahead["fr"]}   # its own rear wheel, the other car's front one
    side = _side_box(cam, contacts[0], contacts[1], PRIOR)
    assert side.length / PRIOR.length > SIDE_LENGTH_BAND[1]          # a 10 m "side"
    assert not side_fits_box(cam, side, np.array(vehicle), PRIOR)
    est = estimate_frame([(rec, cam)], PRIOR, contacts=[contacts])
    assert [e.evidence for e in est] == ["box"]                      # fitted from the vehicle box alone
    assert est[0].box.length == PRIOR.length and est[0].role_vote == 0.0
    assert math.hypot(est[0].box.x - car.x, est[0].box.y - car.y) < math.hypot(side.x - car.x, side.y - car.y) - 1.0


def test_a_long_couple_that_fits_its_box_stays_a_side():
    cam = _camera()
    scale = 1.6
    bus = Box3D(0.5, 5.5, PRIOR.length * scale, 0.0, 0.05)
    u = np.array([math.cos(bus.yaw), math.sin(bus.yaw)])
    n = np.array([-u[1], u[0]])
    lateral = _size(PRIOR, scale)[1] / 2 - PRIOR.track_inset
    rear, front = (np.array([bus.x, bus.y]) + a * u * PRIOR.wheelbase * scale / 2 - n * lateral for a in (-1, 1))
    side = _side_box(cam, rear, front, PRIOR)
    assert side.length / PRIOR.length > SIDE_LENGTH_BAND[1]
    vbox = _seen(cam, bus, scale)
    assert side_fits_box(cam, side, vbox, PRIOR)
    rec = Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                 boxes=np.array([[10, 10, 20, 20, 0.8, 1, 0], [30, 10, 40, 20, 0.7, 1, 1], [*vbox[:4], 0.9, 0, 2]]),
                 relations=[(2, 0, None), (2, 1, None)], wheel_pairs=[(0, 1)])
    est = estimate_frame([(rec, cam)], PRIOR, contacts=[{0: rear, 1: front}])
    assert [e.evidence for e in est] == ["side"] and est[0].box.length == side.length
    # only the left and right edges count: a box taller than the car-shaped silhouette (a bus's body is a box, its
    # roof higher than a car's cabin) still takes the couple
    taller = vbox.copy()
    taller[1] = vbox[1] - 0.5 * (vbox[2] - vbox[0])
    pred = silhouette_boxes(cam, [[side.x, side.y]], [side.yaw], _size(PRIOR, side.length / PRIOR.length), PRIOR.shape)
    assert silhouette_cost(pred, taller)[0] > SIDE_FIT_MAX_COST >= silhouette_cost(pred, taller, edges=[0, 2])[0]
    assert side_fits_box(cam, side, taller, PRIOR)


def test_a_couple_of_about_the_priors_length_is_a_side_whatever_its_box():
    cam = _camera()
    c = _contacts(Box3D(1.0, 5.5, PRIOR.length, PRIOR.width, 0.0))
    side = _side_box(cam, c["rr"], c["fr"], PRIOR)
    assert SIDE_LENGTH_BAND[0] <= side.length / PRIOR.length <= SIDE_LENGTH_BAND[1]
    elsewhere = np.array([500.0, 10.0, 560.0, 60.0, 1.0, 0, 0])   # a box the footprint does not explain at all
    assert side_fits_box(cam, side, elsewhere, PRIOR)


def _estimate(x, y, image, vehicle_box_id, evidence="box", confidence=0.3):
    return Estimate(box=Box3D(x, y, 4.5, 1.8, 0.0), evidence=evidence, camera=image[0], vehicle_box_id=vehicle_box_id,
                    image=image, confidence=confidence)


def test_two_vehicle_boxes_of_one_image_stay_two_vehicles():
    # two vehicles' estimates 1.2 m apart (within the fusion radius): from one image they are two vehicles
    a, b = _estimate(0.0, 5.0, "l.png", 0), _estimate(1.2, 5.0, "l.png", 1)
    assert len(fuse_frame([a, b], radius_m=1.5)) == 2
    # from two cameras they are one vehicle seen twice
    assert len(fuse_frame([a, _estimate(1.2, 5.0, "f.png", 1)], radius_m=1.5)) == 1
    # a couple without a vehicle box joins the vehicle box of its own image that it lies beside
    orphan = _estimate(0.3, 5.0, "l.png", None, evidence="side", confidence=0.45)
    fused = fuse_frame([a, orphan], radius_m=1.5)
    assert len(fused) == 1 and fused[0][1][0] is orphan


def test_a_vehicle_no_camera_sees_a_wheel_of_rests_on_its_most_confident_view_and_one_with_wheels_on_their_mean():
    # two cameras' no-wheel fits of one car, 0.8 m apart: the footprint is the better-trusted one's (a fit's trust
    # falls with its silhouette cost), not their mean, which a poorly fitting view (cut by the image circle) drags
    whole, cut = _estimate(0.0, 5.0, "f.png", 0, confidence=0.28), _estimate(0.8, 5.0, "l.png", 0, confidence=0.05)
    for order in ([whole, cut], [cut, whole]):
        (box, group), = fuse_frame(order, radius_m=1.5)
        assert len(group) == 2 and (box.x, box.y) == (0.0, 5.0)
    # two one-side estimates: their mean, whatever their confidences
    a, b = _estimate(0.0, 5.0, "f.png", 0, "side", 0.9), _estimate(0.8, 5.0, "l.png", 0, "side", 0.2)
    (box, _), = fuse_frame([a, b], radius_m=1.5)
    assert math.isclose(box.x, 0.4) and math.isclose(box.y, 5.0)
