"""What a frame's couples and vehicle boxes say beyond each vehicle's own wheels: a couple no vehicle box owns is a
side of a vehicle the detector missed, a couple shorter than any wheelbase is no side, and two vehicle boxes of one
image are two vehicles however close their estimates lie."""

import math

import numpy as np
import pytest

from deepword.footprint import (
    EVIDENCE_CONFIDENCE,
    MIN_COUPLE_SHARE,
    ORPHAN_CONFIDENCE,
    Estimate,
    estimate_frame,
    fuse_frame,
    plausible_wheels,
)
from deepword.format_3d import Box3D
from deepword.word_format import Record
from tests.stages.bev.test_bev import PRIOR, _camera, _contacts
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
