"""Which way a vehicle faces, as an image shows it: the direction (a unit vector in image pixels) in which its axis
runs forward where it stands, from where the ground point a quarter of its length behind its centre projects to where
the one a quarter ahead does. The facing network learns it from each vehicle box's crop (stages/facing: headlights
against tail lights, where the cabin sits; docs/bev.md, "Front and back"), the detector optionally from its feature map
(docs/detector.md, "Facing"); the footprints read it to tell a vehicle's front from its back
(deepword/footprint.py: ``facing_vote``), where the wheels' roles are near chance.

Defined in the image, not as an angle in the ground plane, so that it needs no calibration at inference and follows
the image through augmentation: a horizontal flip negates its x, a rescale or crop leaves it; the footprints compare
it with the same projection of an estimate's heading through the camera that saw it. A vehicle seen end-on still has
one: the nearer of two ground points projects lower in the picture. On the ground rather than between the faces'
centres: those lie at half the vehicle's height, within a few decimetres of a camera's (0.66-1.0 m on the car), so
seen end-on, whether the near face projects above or below the far one turns on a height an estimate only guesses.
Measured on the quick profile's test vehicles within 10 m, a footprint estimated from the vehicle box alone pointed
its image direction the other way than its truth's for 9-12 % of them between the faces, 2-5 % on the ground. A
quarter of the length rather than the ends: an end of a vehicle close beside the car more often leaves the camera's
field of view (estimates without a direction 9-37 % -> 0-21 % by evidence).

A record carries the vectors under ``extra["facing"]``: {vehicle box_id (str): [dx, dy]}, unnormalised (their length
is the network's certainty): the detector's in a detection record, the facing network's (which replace them) where the
footprints are estimated, with ``extra["facing_acc"]``: the share of val vehicles its vectors point the right way for,
which is how far the footprints trust them.
"""

from __future__ import annotations

import math

import numpy as np

FACING_KEY = "facing"     # a record's extra key: {box_id: [dx, dy]}
FACING_ACC_KEY = "facing_acc"  # a record's extra key: the measured share (0-1) of the vectors that point the right way
MIN_SPAN_PX = 1.0         # points projecting closer than this (far away, tiny) give no direction
AXIS_REACH = 0.25         # the two ground points lie this share of the vehicle's length behind and ahead of its centre


def image_facing(cam, x: float, y: float, yaw: float, length: float) -> np.ndarray | None:
    """The unit image vector from the projection of the ground point ``AXIS_REACH`` x ``length`` behind the vehicle's
    centre to the one as far ahead, or None where either lies outside the camera's field of view or they project less
    than ``MIN_SPAN_PX`` apart. ``cam``: a ``deepword.cameras.Camera``; the vehicle in its vehicle frame (centre x, y,
    yaw over 360 deg pointing to the front, length in metres)."""
    u = np.array([math.cos(yaw), math.sin(yaw)]) * (AXIS_REACH * length)
    points = np.array([[x + u[0], y + u[1], 0.0], [x - u[0], y - u[1], 0.0]])
    uv, seen = cam.project(points)
    if not bool(np.all(seen)):
        return None
    d = uv[0] - uv[1]
    span = float(np.hypot(d[0], d[1]))
    if not math.isfinite(span) or span < MIN_SPAN_PX:
        return None
    return d / span


def record_facing(record) -> dict[int, list[float]]:
    """A record's facing vectors ({vehicle box_id: [dx, dy]}); empty where no network wrote any."""
    return {int(k): v for k, v in (record.extra.get(FACING_KEY) or {}).items()}


def record_facing_accuracy(record, default: float) -> float:
    """How often a record's facing vectors point the right way, as measured on val by whoever wrote them
    (``FACING_ACC_KEY``), else ``default``."""
    acc = record.extra.get(FACING_ACC_KEY)
    return float(acc) if acc is not None else float(default)


def with_facing(extra: dict, facing: dict[int, np.ndarray], accuracy: float) -> dict:
    """``extra`` with the vectors ``facing`` ({box_id: (2,)}) and their measured accuracy (0-1) in place of any earlier
    ones (a detection record's)."""
    vectors = {str(int(k)): [round(float(v[0]), 4), round(float(v[1]), 4)] for k, v in facing.items()}
    return {**extra, FACING_KEY: vectors, FACING_ACC_KEY: round(float(accuracy), 4)}


def box_facings(record) -> np.ndarray:
    """(N, 2) per box of ``record``: the unit image vector from its vehicle's rear to its front (``image_facing``,
    from the record's ``calibration`` and ``objects_3d``), NaN for wheels, for vehicles without 3D truth or too far
    to tell, and for every box of a record without either key (a team's images labelled in 2D): what the facing
    network and the detector's facing head learn from (the boxes that have one) and what the bev stage scores
    their vectors against."""
    from deepword.format_3d import has_3d_truth, record_camera, record_objects_3d

    out = np.full((len(record.boxes), 2), np.nan, dtype=np.float32)
    if not has_3d_truth(record):
        return out
    cam = record_camera(record, "facing targets")
    vehicles, _ = record_objects_3d(record, "facing targets")
    for i, box_id in enumerate(record.box_ids):
        v = vehicles.get(int(box_id))
        if v is not None and int(record.class_ids[i]) == 0:
            d = image_facing(cam, v.x, v.y, v.yaw, v.length)
            if d is not None:
                out[i] = d
    return out
