"""The optional 3D keys of a WORD-style record (docs/design.md §4): ``calibration`` and ``objects_3d``.

The reader (``deepword.word_format.parse_record``) calls ``check_optional_3d`` on every record, so a bad
calibration or 3D box is reported with file, line and field like any other problem; a record without
them is valid. Stages that need them get them through ``record_camera`` and ``record_objects_3d``, which
say which record lacks them.

    "calibration": {"intrinsic": {"model": <a deepword.cameras.LENS_MODELS name>, ..., "width": W, "height": H},
                    "extrinsic": {"quaternion": [qx, qy, qz, qw], "translation": [x, y, z]},
                    "ego_body": [[[x, y], ...], ...]}   # optional: polygons where the ego's own body covers the image
    "objects_3d": {"<vehicle box_id>": {"center": [x, y, z], "size": [l, w, h], "yaw": rad},
                   "<wheel box_id>": {"contact": [x, y]}}

Camera models and conventions: ``deepword.cameras``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from deepword.cameras import LENS_MODELS, Camera, camera_from_calibration

VEHICLE, WHEEL = 0, 1  # class ids of docs/design.md §4 (deepword.word_format imports this module)


def _number(x) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)


def _vector(x, n: int) -> bool:
    return isinstance(x, list) and len(x) == n and all(_number(v) for v in x)


def check_calibration(cal, width: int, height: int, fail: Callable[[str, str], None]) -> None:
    """Validate a ``calibration`` value; ``fail(field, message)`` raises."""
    if not isinstance(cal, dict):
        fail("calibration", "must be an object with 'intrinsic' and 'extrinsic'")
    intr, ext = cal.get("intrinsic"), cal.get("extrinsic")
    if not isinstance(intr, dict):
        fail("calibration.intrinsic", "missing or not an object")
    if not isinstance(ext, dict):
        fail("calibration.extrinsic", "missing or not an object")
    model = intr.get("model")
    if not isinstance(model, str) or model not in LENS_MODELS:
        fail("calibration.intrinsic.model", f"must be one of {tuple(LENS_MODELS)}, got {model!r}")
    lens_model = LENS_MODELS[model]   # its fields and their checks come from the model's class (deepword.cameras)
    names = lens_model.fields
    for name in (*names, "width", "height"):
        if name not in intr:
            fail(f"calibration.intrinsic.{name}", f"missing (the {model} model needs {', '.join(names)}, width, height)")
        if not _number(intr[name]):
            fail(f"calibration.intrinsic.{name}", f"must be a finite number, got {intr[name]!r}")
    for name, size in (("width", width), ("height", height)):
        if int(intr[name]) != size or intr[name] != int(intr[name]):
            fail(f"calibration.intrinsic.{name}", f"{intr[name]!r} but the image is {width}x{height}")
    for name in lens_model.positive:
        if intr[name] <= 0:
            fail(f"calibration.intrinsic.{name}", f"must be positive, got {intr[name]!r}")
    if "fov_deg" in intr and (not _number(intr["fov_deg"]) or not 0 < intr["fov_deg"] <= 360):
        fail("calibration.intrinsic.fov_deg", f"must be a number in (0, 360], got {intr['fov_deg']!r}")
    q = ext.get("quaternion")
    if not _vector(q, 4):
        fail("calibration.extrinsic.quaternion", f"must be [qx, qy, qz, qw] (four finite numbers), got {q!r}")
    if not 0.5 < math.sqrt(sum(v * v for v in q)) < 2.0:
        fail("calibration.extrinsic.quaternion", f"is not a rotation (norm {math.sqrt(sum(v * v for v in q)):.3g}, want 1)")
    t = ext.get("translation")
    if not _vector(t, 3):
        fail("calibration.extrinsic.translation", f"must be [x, y, z] in metres, got {t!r}")
    if "ego_body" in cal:
        check_ego_body(cal["ego_body"], width, height, fail)
    try:
        camera_from_calibration(cal)
    except ValueError as exc:  # e.g. a lens polynomial that never increases
        fail("calibration.intrinsic", str(exc))


def check_ego_body(polygons, width: int, height: int, fail: Callable[[str, str], None]) -> None:
    """Validate ``calibration.ego_body``: a list of polygons of at least three image points [x, y] (box
    coordinates: 0..width, 0..height), where the ego vehicle's own body covers the image."""
    if not isinstance(polygons, list):
        fail("calibration.ego_body", f"must be a list of polygons (lists of [x, y] image points), got {polygons!r}")
    for i, polygon in enumerate(polygons):
        if not isinstance(polygon, list) or len(polygon) < 3:
            fail(f"calibration.ego_body[{i}]", "must be a polygon of at least three [x, y] image points")
        for j, point in enumerate(polygon):
            if not _vector(point, 2):
                fail(f"calibration.ego_body[{i}][{j}]", f"must be [x, y] (two finite numbers), got {point!r}")
            if not (-1 <= point[0] <= width + 1 and -1 <= point[1] <= height + 1):
                fail(f"calibration.ego_body[{i}][{j}]", f"{point!r} lies outside the {width}x{height} image")


def check_objects_3d(objs, class_of: dict[int, int], fail: Callable[[str, str], None]) -> None:
    """Validate an ``objects_3d`` value against the record's boxes (``class_of``: box_id -> class_id)."""
    if not isinstance(objs, dict):
        fail("objects_3d", "must be an object keyed by box_id")
    for key, entry in objs.items():
        fld = f"objects_3d.{key}"
        try:
            bid = int(key)
        except ValueError:
            fail(fld, "keys must be box ids (integers as strings)")
        if bid not in class_of:
            fail(fld, f"box_id {bid} does not exist")
        if not isinstance(entry, dict):
            fail(fld, "must be an object")
        if class_of[bid] == VEHICLE:
            if not _vector(entry.get("center"), 3):
                fail(f"{fld}.center", f"a vehicle needs center [x, y, z] in metres, got {entry.get('center')!r}")
            size = entry.get("size")
            if not _vector(size, 3) or min(size) <= 0:
                fail(f"{fld}.size", f"a vehicle needs size [length, width, height] > 0, got {size!r}")
            if not _number(entry.get("yaw")):
                fail(f"{fld}.yaw", f"a vehicle needs a yaw in radians, got {entry.get('yaw')!r}")
        elif not _vector(entry.get("contact"), 2):
            fail(f"{fld}.contact", f"a wheel needs its ground contact [x, y] in metres, got {entry.get('contact')!r}")


def check_optional_3d(obj: dict, class_of: dict[int, int], width: int, height: int,
                      fail: Callable[[str, str], None]) -> None:
    """The reader's hook: validate whichever of the two keys the record has."""
    if "calibration" in obj:
        check_calibration(obj["calibration"], width, height, fail)
    if "objects_3d" in obj:
        check_objects_3d(obj["objects_3d"], class_of, fail)


# --- access for the stages that need them --------------------------------------------------------------

class Missing3DError(ValueError):
    """A record lacks a key a 3D stage needs; names the file and line."""


def _where(record) -> str:
    file, line = record.source or (record.image, None)
    return f"{file}:{line}" if line else str(file)


def has_3d_truth(record) -> bool:
    """The record carries both 3D keys (``calibration`` and ``objects_3d``): what the footprints are scored against and
    the facing network learns from; a team's 2D labels carry neither."""
    return "calibration" in record.extra and "objects_3d" in record.extra


def record_camera(record, needed_by: str) -> Camera:
    """The record's calibrated camera, or Missing3DError naming the file, line and who needs it."""
    cal = record.extra.get("calibration")
    if cal is None:
        raise Missing3DError(f"{_where(record)}: field 'calibration': missing ({record.image}); {needed_by} needs "
                             "each image's camera calibration (docs/design.md §4, docs/bev.md)")
    return camera_from_calibration(cal, name=record.camera)


@dataclass(frozen=True)
class Box3D:
    """A vehicle's footprint and height in the vehicle frame: centre (x, y), length, width, yaw."""

    x: float
    y: float
    length: float
    width: float
    yaw: float
    height: float = 0.0

    def corners(self) -> np.ndarray:
        """(4, 2): front-left, front-right, rear-right, rear-left."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hx, hy = self.length / 2, self.width / 2
        local = np.array([[hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]])
        return local @ np.array([[c, s], [-s, c]]) + np.array([self.x, self.y])

    def to_json(self) -> dict:
        return {"center": [round(self.x, 4), round(self.y, 4), round(self.height / 2, 4)],
                "size": [round(self.length, 4), round(self.width, 4), round(self.height, 4)],
                "yaw": round(self.yaw, 5)}


def record_objects_3d(record, needed_by: str) -> tuple[dict[int, Box3D], dict[int, tuple[float, float]]]:
    """(vehicle box_id -> Box3D, wheel box_id -> contact (x, y)) of the record's ``objects_3d``, or
    Missing3DError naming the file and line."""
    objs = record.extra.get("objects_3d")
    if objs is None:
        raise Missing3DError(f"{_where(record)}: field 'objects_3d': missing ({record.image}); {needed_by} needs "
                             "the 3D truth of the vehicles and wheels (docs/design.md §4, docs/bev.md)")
    vehicles, wheels = {}, {}
    for key, entry in objs.items():
        if "contact" in entry:
            wheels[int(key)] = (float(entry["contact"][0]), float(entry["contact"][1]))
        else:
            (x, y, _), (ln, wd, ht) = entry["center"], entry["size"]
            vehicles[int(key)] = Box3D(float(x), float(y), float(ln), float(wd), float(entry["yaw"]), float(ht))
    return vehicles, wheels
