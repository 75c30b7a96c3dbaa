"""One vehicle, two footprints: a weak footprint (one wheel or none) whose view another footprint explains joins it
(``deepword.footprint.absorb_explained``); another vehicle's box, a wheel that stands elsewhere, two boxes of one
image never do."""

import math

import numpy as np
import pytest

from deepword.footprint import (
    Estimate,
    explained_cost,
    footprints_from_contacts,
    fuse_frame,
    silhouette_boxes,
)
from deepword.format_3d import Box3D
from stages.data.camera import nominal_camera
from tests.stages.bev.test_bev import LEFT, PRIOR, _camera, _contacts, _record

CAR = Box3D(8.0, 2.6, 4.5, 1.8, 0.05, 1.5)


def _front():
    return nominal_camera("front", {**LEFT, "yaw_deg": 0.0, "pitch_deg": 23.0, "position": [3.7, 0.0, 0.66]},
                          640, 480, [640, 480])


def _seen(cam, car: Box3D) -> tuple[float, float, float, float]:
    """The box a camera sees of ``car``: its silhouette (the prior's shape)."""
    box = silhouette_boxes(cam, [[car.x, car.y]], [car.yaw], (car.length, car.width, car.height), PRIOR.shape)[0]
    return tuple(float(v) for v in box)


def _weak(cam, camera: str, seen, at: Box3D, evidence: str = "box", contacts=(), vehicle: int = 0) -> Estimate:
    return Estimate(box=at, evidence=evidence, camera=camera, vehicle_box_id=vehicle,
                    image=f"images/{camera}/000000.png", confidence=0.3 if evidence == "box" else 0.5, cam=cam,
                    vbox=seen, contacts=tuple(contacts))


def _along_ray(cam, car: Box3D, metres: float) -> Box3D:
    """``car`` moved ``metres`` further from ``cam`` along its ray: where a weak view's error lies."""
    ray = np.array([car.x, car.y]) - cam.translation[:2]
    x, y = np.array([car.x, car.y]) + metres * ray / np.linalg.norm(ray)
    return Box3D(float(x), float(y), car.length, car.width, car.yaw, car.height)


def _side(left) -> Estimate:
    """The left camera's footprint of CAR from its two right wheels (the true footprint)."""
    rec = _record(left, [(0, 1, None), (0, 2, None)], [(1, 2)], n_vehicles=1, n_wheels=2)
    contacts = _contacts(CAR)
    (side,) = footprints_from_contacts(rec, left, PRIOR, {1: contacts["rr"], 2: contacts["fr"]})
    assert side.evidence == "side" and math.hypot(side.box.x - CAR.x, side.box.y - CAR.y) < 1e-9
    return side


def test_a_displaced_view_of_a_vehicle_joins_the_footprint_that_explains_it():
    left, front = _camera(), _front()
    side = _side(left)
    box = _weak(front, "front", _seen(front, CAR), _along_ray(front, CAR, 2.5))
    assert explained_cost(side.box, box, PRIOR) < 1e-6
    assert len(fuse_frame([side, box], 1.5)) == 2             # 2.5 m apart: two footprints by distance alone
    (fused, group), = fuse_frame([side, box], 1.5, PRIOR)      # the side footprint draws what the front camera saw
    assert fused == side.box and [e.evidence for e in group] == ["side", "box"]


def test_another_vehicle_a_wheel_elsewhere_or_a_second_box_of_one_image_stays_apart():
    left, front = _camera(), _front()
    side = _side(left)
    # the front camera sees another car, 3 m to the left of the first: the side footprint does not draw it
    other = Box3D(CAR.x, CAR.y + 3.0, CAR.length, CAR.width, CAR.yaw, CAR.height)
    assert len(fuse_frame([side, _weak(front, "front", _seen(front, other), _along_ray(front, other, 0.5))], 1.5,
                          PRIOR)) == 2
    # a one-wheel view drawn alike, but its wheel stands 3 m behind the car: not this car's wheel
    wheel_at = (CAR.x - 5.0, CAR.y)
    displaced = _along_ray(front, CAR, 2.5)
    wheel = _weak(front, "front", _seen(front, CAR), displaced, "wheel", [wheel_at])
    assert len(fuse_frame([side, wheel], 1.5, PRIOR)) == 2
    on_car = _weak(front, "front", _seen(front, CAR), displaced, "wheel", [tuple(_contacts(CAR)["rl"])])
    assert len(fuse_frame([side, on_car], 1.5, PRIOR)) == 1
    # a second vehicle box of the left image is a second vehicle, however well the footprint draws it
    twin = _weak(left, "left", _seen(left, CAR), _along_ray(left, CAR, 2.5), vehicle=1)
    assert twin.image == side.image and len(fuse_frame([side, twin], 1.5, PRIOR)) == 2


def test_between_two_weak_footprints_the_one_that_explains_both_views_stays():
    left, front = _camera(), _front()
    right_place = _weak(left, "left", _seen(left, CAR), CAR)
    # the front camera's fit went 2.5 m towards the ego: it comes first in the fusion's order (nearer), yet the left
    # view's footprint draws both boxes and the front one's does not draw the left camera's box
    wrong_place = _weak(front, "front", _seen(front, CAR), _along_ray(front, CAR, -2.5))
    assert math.hypot(wrong_place.box.x, wrong_place.box.y) < math.hypot(CAR.x, CAR.y)
    assert explained_cost(right_place.box, wrong_place, PRIOR) < explained_cost(wrong_place.box, right_place, PRIOR)
    (fused, group), = fuse_frame([right_place, wrong_place], 1.5, PRIOR)
    assert fused == CAR and {e.camera for e in group} == {"left", "front"}


def test_a_one_wheel_footprint_is_as_confident_as_its_box_tells_the_wheels_end(monkeypatch):
    import deepword.footprint as footprint
    from deepword.word_format import Record

    left = _camera()
    car = Box3D(1.5, 5.0, 4.5, 1.8, 0.05, 1.5)
    contact = _contacts(car)["rr"]
    whole = np.array(_seen(left, car))

    def one_wheel():
        rec = Record(image="images/left/000000.png", frame_id=0, camera="left", width=left.width, height=left.height,
                     boxes=np.array([[*whole, 1.0, 0, 0], [0.0, 0.0, 10.0, 10.0, 1.0, 1, 1]]), relations=[(0, 1, None)],
                     wheel_pairs=[])
        (e,) = footprints_from_contacts(rec, left, PRIOR, {1: contact})
        assert e.evidence == "wheel"
        return e

    # the whole side in view: the other end draws the box far worse, and the footprint keeps a wheel's 0.5
    seen = one_wheel()
    assert math.hypot(seen.box.x - car.x, seen.box.y - car.y) < 0.5
    assert footprint.end_margin(left, contact, seen.box, 0.0, whole, PRIOR) > 3 * footprint.END_MARGIN_SCALE
    assert seen.confidence == pytest.approx(0.5, abs=0.01)
    assert footprint.end_margin(left, contact, seen.box, 1e6, whole, PRIOR) == 0.0   # never negative
    # a box either end draws alike (a margin of 0) leaves the footprint no confidence; half the scale, 1 - e^-0.5
    monkeypatch.setattr(footprint, "end_margin", lambda *args: 0.0)
    assert one_wheel().confidence == 0.0
    monkeypatch.setattr(footprint, "end_margin", lambda *args: footprint.END_MARGIN_SCALE / 2)
    assert one_wheel().confidence == pytest.approx(0.5 * (1 - math.exp(-0.5)))
