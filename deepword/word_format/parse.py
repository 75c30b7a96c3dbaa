"""The validator: one decoded JSON object of a labels file -> a ``Record``, or a ``DatasetError`` naming
file, line and field of the first problem (docs/design.md §4)."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import numpy as np

from deepword.format_3d import check_optional_3d
from deepword.word_format.record import CAMERAS, ROLES, VEHICLE, WHEEL, DatasetError, Record

REQUIRED_KEYS = ("image", "frame_id", "camera", "width", "height", "boxes", "relations")


def _is_number(x) -> bool:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:  # an integer too large for a float (JSON allows any length)
        return False


def _is_int(x) -> bool:
    return (isinstance(x, int) and not isinstance(x, bool)) or (isinstance(x, float) and x.is_integer())


def parse_record(obj, file: str, line: int | None, root: Path | None = None, check_bounds: bool = True) -> Record:
    """Validate one decoded JSON object and turn it into a Record; raise DatasetError on the first problem."""

    def fail(fld: str, msg: str):
        raise DatasetError(file, line, fld, msg)

    if not isinstance(obj, dict):
        fail("<record>", f"expected a JSON object, got {type(obj).__name__}")
    for key in REQUIRED_KEYS:
        if key not in obj:
            fail(key, "missing")
    image = _image_path(obj["image"], root, fail)
    if not _is_int(obj["frame_id"]):
        fail("frame_id", f"must be an integer, got {obj['frame_id']!r}")
    if obj["camera"] not in CAMERAS:
        fail("camera", f"must be one of {CAMERAS}, got {obj['camera']!r}")
    for key in ("width", "height"):
        if not _is_int(obj[key]) or obj[key] <= 0:
            fail(key, f"must be a positive integer, got {obj[key]!r}")
    width, height = int(obj["width"]), int(obj["height"])
    boxes = _boxes(obj["boxes"], width, height, check_bounds, fail)
    cls_of = {int(b): int(c) for c, b in zip(boxes[:, 5], boxes[:, 6], strict=True)}
    relations = _relations(obj["relations"], cls_of, fail)
    pairs = _wheel_pairs(obj.get("wheel_pairs", []), cls_of, fail)
    check_optional_3d(obj, cls_of, width, height, fail)  # calibration, objects_3d: only when present

    ignore = _ignore_regions(obj.get("ignore", []), width, height, check_bounds, fail)

    known = set(REQUIRED_KEYS) | {"scene", "wheel_pairs", "ignore"}
    extra = {k: v for k, v in obj.items() if k not in known}
    scene = obj.get("scene", "")
    return Record(image=image, frame_id=int(obj["frame_id"]), camera=obj["camera"], width=width, height=height,
                  boxes=boxes, relations=relations, wheel_pairs=pairs, scene=str(scene), extra=extra,
                  source=(str(file), line if line is not None else 0), ignore=ignore)


def _image_path(image, root: Path | None, fail: Callable[[str, str], NoReturn]) -> str:
    """A non-empty relative path that stays inside the dataset root."""
    if not isinstance(image, str) or not image:
        fail("image", "must be a non-empty relative path")
    if "\x00" in image:
        fail("image", f"path {image!r} contains a NUL character")
    if os.path.isabs(image) or ".." in Path(image).parts:
        fail("image", f"path {image!r} leaves the dataset root")
    if root is not None:
        resolved = (root / image).resolve()
        if not resolved.is_relative_to(root.resolve()):
            fail("image", f"path {image!r} leaves the dataset root {root}")
    return image


def _boxes(raw_boxes, width: int, height: int, check_bounds: bool,
           fail: Callable[[str, str], NoReturn]) -> np.ndarray:
    """The (N, 7) box array: ordered corners inside the image, scores in [0, 1], known classes, unique ids."""
    if not isinstance(raw_boxes, list):
        fail("boxes", "must be a list")
    boxes = np.zeros((len(raw_boxes), 7), dtype=np.float64)
    seen_ids: set[int] = set()
    tol = 1.0  # rounding slack at the image border
    for i, box in enumerate(raw_boxes):
        fld = f"boxes[{i}]"
        if not isinstance(box, list) or len(box) != 7:
            fail(fld, "must be [x1, y1, x2, y2, score, class_id, box_id]")
        if not all(_is_number(v) for v in box):
            fail(fld, f"all seven values must be finite numbers, got {box}")
        x1, y1, x2, y2, score, cls, bid = box
        if not x1 < x2:
            fail(fld, f"x1 < x2 required, got x1={x1} x2={x2}")
        if not y1 < y2:
            fail(fld, f"y1 < y2 required, got y1={y1} y2={y2}")
        if check_bounds and (x1 < -tol or y1 < -tol or x2 > width + tol or y2 > height + tol):
            fail(fld, f"box {box[:4]} lies outside the {width}x{height} image")
        if not 0.0 <= score <= 1.0:
            fail(fld, f"score must be in [0, 1], got {score}")
        if not _is_int(cls) or int(cls) not in (VEHICLE, WHEEL):
            fail(fld, f"unknown class_id {cls!r} (0 vehicle, 1 wheel)")
        if not _is_int(bid):
            fail(fld, f"box_id must be an integer, got {bid!r}")
        if int(bid) in seen_ids:
            fail(fld, f"duplicate box_id {int(bid)}")
        seen_ids.add(int(bid))
        boxes[i] = box
    return boxes


def _ignore_regions(raw, width: int, height: int, check_bounds: bool,
                    fail: Callable[[str, str], NoReturn]) -> np.ndarray:
    """The (K, 5) ignore regions: ordered corners inside the image and a known class."""
    if not isinstance(raw, list):
        fail("ignore", "must be a list of [x1, y1, x2, y2, class_id]")
    regions = np.zeros((len(raw), 5), dtype=np.float64)
    tol = 1.0
    for i, region in enumerate(raw):
        fld = f"ignore[{i}]"
        if not isinstance(region, list) or len(region) != 5 or not all(_is_number(v) for v in region):
            fail(fld, f"must be [x1, y1, x2, y2, class_id] of finite numbers, got {region!r}")
        x1, y1, x2, y2, cls = region
        if not (x1 < x2 and y1 < y2):
            fail(fld, f"x1 < x2 and y1 < y2 required, got {region[:4]}")
        if check_bounds and (x1 < -tol or y1 < -tol or x2 > width + tol or y2 > height + tol):
            fail(fld, f"region {region[:4]} lies outside the {width}x{height} image")
        if not _is_int(cls) or int(cls) not in (VEHICLE, WHEEL):
            fail(fld, f"unknown class_id {cls!r} (0 vehicle, 1 wheel)")
        regions[i] = region
    return regions


def _relations(raw_rel, cls_of: dict[int, int],
               fail: Callable[[str, str], NoReturn]) -> list[tuple[int, int, str | None]]:
    """(vehicle, wheel, role) triples between existing boxes of the right classes; at most one owner a wheel."""
    if not isinstance(raw_rel, list):
        fail("relations", "must be a list")
    relations: list[tuple[int, int, str | None]] = []
    owners: dict[int, int] = {}
    for i, rel in enumerate(raw_rel):
        fld = f"relations[{i}]"
        if not isinstance(rel, list) or len(rel) not in (2, 3) or not all(_is_int(v) for v in rel[:2]):
            fail(fld, "must be [vehicle_box_id, wheel_box_id] or [vehicle_box_id, wheel_box_id, role]")
        v, w = int(rel[0]), int(rel[1])
        role = rel[2] if len(rel) == 3 else None
        if v not in cls_of:
            fail(fld, f"vehicle box_id {v} does not exist")
        if w not in cls_of:
            fail(fld, f"wheel box_id {w} does not exist")
        if cls_of[v] != VEHICLE:
            fail(fld, f"box {v} is not a vehicle (class_id {cls_of[v]})")
        if cls_of[w] != WHEEL:
            fail(fld, f"box {w} is not a wheel (class_id {cls_of[w]})")
        if role is not None and role not in ROLES:
            fail(fld, f"role must be one of {ROLES}, got {role!r}")
        if w in owners:
            fail(fld, f"wheel {w} already has owner {owners[w]}")
        owners[w] = v
        relations.append((v, w, role))
    return relations


def _wheel_pairs(raw_pairs, cls_of: dict[int, int], fail: Callable[[str, str], NoReturn]) -> list[tuple[int, int]]:
    """(rear, front) pairs of two different existing wheels."""
    if not isinstance(raw_pairs, list):
        fail("wheel_pairs", "must be a list")
    pairs: list[tuple[int, int]] = []
    for i, pair in enumerate(raw_pairs):
        fld = f"wheel_pairs[{i}]"
        if not isinstance(pair, list) or len(pair) != 2 or not all(_is_int(v) for v in pair):
            fail(fld, "must be [rear_wheel_box_id, front_wheel_box_id]")
        a, b = int(pair[0]), int(pair[1])
        for bid in (a, b):
            if cls_of.get(bid) != WHEEL:
                fail(fld, f"box {bid} is not an existing wheel")
        if a == b:
            fail(fld, "a wheel cannot pair with itself")
        pairs.append((a, b))
    return pairs
