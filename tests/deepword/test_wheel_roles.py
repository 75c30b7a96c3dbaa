"""A wheel's front / rear role read from which way its vehicle faces: along the vehicle box's facing vector in the
image, or along its fused footprint's heading on the ground; the rules' order, the couples rear first, and roles so
written never vote for the heading a second time."""

import math

import numpy as np

from deepword.facing import FACING_KEY
from deepword.footprint import Estimate
from deepword.format_3d import Box3D
from deepword.wheel_roles import (
    FACING,
    FOOTPRINT,
    NETWORK,
    ROLES_FROM_KEY,
    facing_roles,
    footprint_roles,
    network_roles,
    roles_from_front,
    with_roles,
)
from deepword.word_format import VEHICLE, WHEEL, Record


def _record(wheel_xs: list[float], facing: list[float] | None, roles: list[str | None] | None = None) -> Record:
    """A vehicle box (id 1) from x 100 to 300, its wheels (ids 10, 11, ...) 20 px wide centred at ``wheel_xs``."""
    boxes = [[100, 100, 300, 200, 1.0, VEHICLE, 1]]
    boxes += [[x - 10, 170, x + 10, 200, 1.0, WHEEL, 10 + i] for i, x in enumerate(wheel_xs)]
    roles = roles or [None] * len(wheel_xs)
    relations = [(1, 10 + i, roles[i]) for i in range(len(wheel_xs))]
    pairs = [(10, 11)] if len(wheel_xs) == 2 else []
    extra = {FACING_KEY: {"1": facing}} if facing is not None else {}
    return Record(image="a.png", frame_id=0, camera="left", width=400, height=300, boxes=np.array(boxes, float),
                  relations=relations, wheel_pairs=pairs, extra=extra)


def test_two_wheels_apart_are_told_apart_along_the_facing_vector():
    assert facing_roles(_record([130, 270], [1.0, 0.1])) == {(1, 10): "rear", (1, 11): "front"}
    assert facing_roles(_record([130, 270], [-0.8, 0.0])) == {(1, 10): "front", (1, 11): "rear"}


def test_a_lone_wheel_or_wheels_close_together_compare_with_the_box_centre():
    assert facing_roles(_record([270], [1.0, 0.0])) == {(1, 10): "front"}
    assert facing_roles(_record([130], [1.0, 0.0])) == {(1, 10): "rear"}
    # an axle seen end-on: both wheels on the box's rear half, 30 px apart (under a quarter of its 200 px)
    assert facing_roles(_record([130, 160], [1.0, 0.0])) == {(1, 10): "rear", (1, 11): "rear"}


def test_no_facing_vector_no_roles():
    assert facing_roles(_record([130, 270], None)) == {}


def _footprint(yaw: float) -> list:
    box = Box3D(x=5.0, y=2.0, length=4.5, width=1.8, yaw=yaw)
    estimate = Estimate(box=box, evidence="side", camera="left", vehicle_box_id=1, image="a.png")
    other = Estimate(box=box, evidence="side", camera="front", vehicle_box_id=1, image="b.png")
    return [(box, [estimate, other])]


def test_a_wheel_ahead_of_its_footprints_centre_is_a_front_wheel():
    rec = _record([130, 270], None)
    contacts = {10: np.array([3.7, 2.9]), 11: np.array([6.3, 2.9])}
    assert footprint_roles(rec, _footprint(0.0), contacts) == {(1, 10): "rear", (1, 11): "front"}
    assert footprint_roles(rec, _footprint(math.pi), contacts) == {(1, 10): "front", (1, 11): "rear"}
    # a wheel without a ground contact, and a vehicle no footprint of this image holds, get none
    assert footprint_roles(rec, _footprint(0.0), {11: contacts[11]}) == {(1, 11): "front"}
    other_image = [(b, [e for e in g if e.image != "a.png"]) for b, g in _footprint(0.0)]
    assert footprint_roles(rec, other_image, contacts) == {}


def test_the_first_rule_that_names_a_role_decides_and_couples_come_rear_first():
    rec = _record([130, 270, 200], None, roles=["front", "rear", "front"])
    out = with_roles(rec, [(FOOTPRINT, {(1, 10): "rear"}), (FACING, {(1, 10): "front", (1, 11): "front"})])
    assert out.relations == [(1, 10, "rear"), (1, 11, "front"), (1, 12, "front")]
    assert out.extra[ROLES_FROM_KEY] == {FOOTPRINT: 1, FACING: 1, NETWORK: 1}
    flipped = with_roles(_record([130, 270], None), [(FACING, {(1, 10): "front", (1, 11): "rear"})])
    assert flipped.wheel_pairs == [(11, 10)]
    assert rec.relations[0] == (1, 10, "front"), "the input record is left as it was"


def test_roles_read_from_the_heading_do_not_vote_for_it_again():
    rec = _record([130, 270], None, roles=["rear", "front"])
    assert network_roles(rec) == {10: "rear", 11: "front"}
    assert network_roles(with_roles(rec, [(FACING, {})])) == {}


def test_infer_reads_the_footprint_first_then_the_facing_vector():
    rec = _record([130, 270], [-1.0, 0.0], roles=["rear", "rear"])   # the facing vector says the front is at left
    contacts = {11: np.array([6.3, 2.9])}                            # only the second wheel has a ground contact
    out = roles_from_front(rec, _footprint(0.0), contacts)
    assert out.relations == [(1, 10, "front"), (1, 11, "front")]
    assert out.extra[ROLES_FROM_KEY] == {FOOTPRINT: 1, FACING: 1, NETWORK: 0}
    assert roles_from_front(rec).relations == [(1, 10, "front"), (1, 11, "rear")]   # no camera: the vector alone
