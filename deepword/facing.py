"""Which way a vehicle faces, as an image shows it: the direction (a unit vector in image pixels) from where its rear
face's centre projects to where its front face's centre does. The detector learns it from the pixels (its facing head:
headlights against tail lights, the longer overhang; docs/detector.md, "Facing"), the footprints read it to tell a
vehicle's front from its back (deepword/footprint.py: ``facing_vote``), where the wheels' roles are near chance.

Defined in the image, not as an angle in the ground plane, so that it needs no calibration at inference and follows
the image through augmentation: a horizontal flip negates its x, a rescale or crop leaves it; the footprints compare
it with the same projection of an estimate's heading through the camera that saw it. A vehicle seen end-on still has
one: its near face projects lower in the picture than its far face.

A detection record carries the detector's vectors under ``extra["facing"]``: {vehicle box_id (str): [dx, dy]},
unnormalised (their length is the detector's certainty: an L1 fit to unit vectors shrinks where it cannot tell).
"""

from __future__ import annotations

import math

import numpy as np

FACING_KEY = "facing"     # a detection record's extra key: {box_id: [dx, dy]}
MIN_SPAN_PX = 1.0         # faces projecting closer than this (far away, tiny) give no direction


def image_facing(cam, x: float, y: float, yaw: float, length: float, height: float) -> np.ndarray | None:
    """The unit image vector from the projection of the vehicle's rear face centre to its front face centre (both at
    half its height), or None where either lies outside the camera's field of view or they project less than
    ``MIN_SPAN_PX`` apart. ``cam``: a ``deepword.cameras.Camera``; the vehicle in its vehicle frame (centre x, y, yaw
    over 360 deg pointing to the front, length and height in metres)."""
    u = np.array([math.cos(yaw), math.sin(yaw)]) * (length / 2)
    z = height / 2
    faces = np.array([[x + u[0], y + u[1], z], [x - u[0], y - u[1], z]])
    uv, seen = cam.project(faces)
    if not bool(np.all(seen)):
        return None
    d = uv[0] - uv[1]
    span = float(np.hypot(d[0], d[1]))
    if not math.isfinite(span) or span < MIN_SPAN_PX:
        return None
    return d / span


def record_facing(record) -> dict[int, list[float]]:
    """A detection record's facing vectors ({vehicle box_id: [dx, dy]}); empty for a detector without a facing head."""
    return {int(k): v for k, v in (record.extra.get(FACING_KEY) or {}).items()}
