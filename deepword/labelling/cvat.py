"""CVAT for images 1.1 XML: annotations in, predictions out.

Read per ``<image id name width height>``: its ``<box label xtl ytl xbr ybr group_id>`` shapes, labels
``vehicle``/``wheel``. ``group_id`` ties a vehicle to its wheels (exactly one vehicle per group); a wheel's
``<attribute name="role">`` is ``front``, ``rear`` or ``none``; its optional ``<attribute name="couple">`` number
n > 0 pairs it with the other wheel of its group with the same n (0: not stated; see ``deepword.labelling.build``).
Other shapes (polygons, points, ...) are reported, not skipped.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

from deepword.labelling.build import (
    LABEL_OF_CLASS,
    RawBox,
    RawImage,
    RawLink,
    explicit_pairs,
    numbered_couples,
    parse_couple_number,
    parse_role,
    to_number,
)
from deepword.labelling.problems import LabellingError, Problems
from deepword.word_format import VEHICLE, WHEEL, Record

SHAPES = ("polygon", "polyline", "points", "mask", "cuboid", "ellipse", "skeleton", "tag")


def read_cvat(path: Path, problems: Problems) -> tuple[list[RawImage], list[str]]:
    try:
        root = ET.parse(path).getroot()
    except OSError as exc:
        raise LabellingError(f"{path}: cannot be read: {exc.strerror}") from None
    except ET.ParseError as exc:
        raise LabellingError(f"{path}: not an XML file: {exc}") from None
    if root.tag != "annotations":
        raise LabellingError(f"{path}: not a CVAT for images XML file (root <{root.tag}>, expected <annotations>)")
    version = (root.findtext("version") or "").strip()
    images = []
    for k, el in enumerate(root.findall("image")):
        name = el.get("name")
        where = f"image {name!r}" if name else f"image #{k + 1}"
        if not name:
            problems.add(where, "name", "missing")
            continue
        img = RawImage(where=where, name=name, name_field="name")
        for fld in ("width", "height"):
            if el.get(fld) is not None:
                value = to_number(el.get(fld), where, fld, problems)
                setattr(img, fld, int(value) if value is not None else None)
        _read_boxes(img, el, problems)
        images.append(img)
    notes = [f"CVAT XML version {version or '(none given)'}"]
    if version and version != "1.1":
        notes.append("read as CVAT for images 1.1")
    return images, notes


def _read_boxes(img: RawImage, el: ET.Element, problems: Problems) -> None:
    groups: dict[int, list[tuple[RawBox, str | None, str]]] = defaultdict(list)
    roles: list[tuple[RawBox, str | None, int]] = []
    numbered = []
    for j, child in enumerate(el):
        if child.tag in SHAPES:
            problems.add(f"{img.where}, <{child.tag}> #{j + 1}", "<shape>",
                         f"unsupported shape <{child.tag}> (boxes only)")
            continue
        if child.tag != "box":
            continue
        k = len(img.boxes)
        label = child.get("label", "")
        where = f"{img.where}, box {k} ({label})"
        fields = ("xtl", "ytl", "xbr", "ybr")
        nums = [to_number(child.get(f), where, f, problems) for f in fields]
        attrs = {a.get("name"): (a.text or "") for a in child.findall("attribute")}
        ok_role, role = parse_role(attrs.get("role"), where, "attribute 'role'", problems)
        couple = parse_couple_number(attrs.get("couple"), where, "attribute 'couple'", problems)
        group = child.get("group_id")
        gid = 0
        if group not in (None, ""):
            g = to_number(group, where, "group_id", problems)
            gid = int(g) if g is not None else -1
        if any(n is None for n in nums) or not ok_role or couple is None or gid < 0:
            continue
        rotation = to_number(child.get("rotation") or 0, where, "rotation", problems)
        if rotation is None or abs((rotation + 180) % 360 - 180) > 0.01:
            if rotation is not None:
                problems.add(where, "rotation", f"rotated boxes are not supported (rotation {rotation})")
            continue
        box = RawBox(key=str(k), where=where, label=label, label_field="label", coords=tuple(nums),
                     coord_fields=fields)
        img.boxes.append(box)
        kind = label.strip().lower()
        if gid:
            groups[gid].append((box, kind, where))
        if kind == "wheel":
            roles.append((box, role, gid))
            numbered.append((gid or None, couple, box, "attribute 'couple'"))
        elif role is not None:
            problems.add(where, "attribute 'role'", "a role belongs to a wheel, not a vehicle")
    vehicle_of: dict[int, RawBox] = {}
    for gid, members in groups.items():
        vehicles = [b for b, kind, _ in members if kind == "vehicle"]
        if len(vehicles) != 1:
            names = ", ".join(f"box {b.key}" for b in vehicles)
            msg = "has no vehicle" if not vehicles else f"has {len(vehicles)} vehicles ({names})"
            problems.add(members[0][2], "group_id", f"group {gid} {msg}: exactly one vehicle per group")
            continue
        vehicle_of[gid] = vehicles[0]
    for box, role, gid in roles:
        if gid and gid in vehicle_of:
            img.links.append(RawLink(box.key, vehicle_of[gid].key, role, box.where, "group_id"))
        elif not gid and role is not None:
            problems.add(box.where, "attribute 'role'", f"role {role!r} given but the wheel has no vehicle "
                                                        f"(no group_id)")
    numbered_couples(img, numbered, problems)


def _meta(n_images: int) -> ET.Element:
    meta = ET.Element("meta")
    task = ET.SubElement(meta, "task")
    ET.SubElement(task, "name").text = "deepword"
    ET.SubElement(task, "size").text = str(n_images)
    ET.SubElement(task, "mode").text = "annotation"
    labels = ET.SubElement(task, "labels")
    for name in (LABEL_OF_CLASS[VEHICLE], LABEL_OF_CLASS[WHEEL]):
        label = ET.SubElement(labels, "label")
        ET.SubElement(label, "name").text = name
        ET.SubElement(label, "type").text = "rectangle"
        attributes = ET.SubElement(label, "attributes")
        if name == "wheel":
            for aname, kind, default, values in (("role", "select", "none", "none\nfront\nrear"),
                                                  ("couple", "number", "0", "0\n9\n1")):
                attr = ET.SubElement(attributes, "attribute")
                ET.SubElement(attr, "name").text = aname
                ET.SubElement(attr, "mutable").text = "False"
                ET.SubElement(attr, "input_type").text = kind
                ET.SubElement(attr, "default_value").text = default
                ET.SubElement(attr, "values").text = values
    return meta


def to_cvat(records: list[Record]) -> tuple[str, list[str]]:
    """CVAT for images 1.1 XML of the records (boxes, ``group_id`` per vehicle, wheels' ``role`` and, where the roles
    do not give them, ``couple`` numbers), and notes on what the format cannot carry. Scores are not kept: CVAT
    boxes have none."""
    root = ET.Element("annotations")
    ET.SubElement(root, "version").text = "1.1"
    root.append(_meta(len(records)))
    lost = cross = 0
    for i, rec in enumerate(records):
        el = ET.SubElement(root, "image", id=str(i), name=rec.image, width=str(rec.width), height=str(rec.height))
        owner = rec.owner_of()
        role = {w: r for _, w, r in rec.relations}
        vehicles = [int(b) for b, c in zip(rec.box_ids, rec.class_ids, strict=True) if c == VEHICLE]
        group = {v: g for g, v in enumerate(vehicles, start=1)}
        stated, n_lost = explicit_pairs(rec)
        lost += n_lost
        number: dict[int, int] = {}
        per_scope: dict[object, int] = defaultdict(int)
        for rear, front in sorted(stated):
            scope_a, scope_b = owner.get(rear), owner.get(front)
            if scope_a != scope_b:
                cross += 1
                continue
            per_scope[scope_a] += 1
            number[rear] = number[front] = per_scope[scope_a]
        for x1, y1, x2, y2, _, cls, bid in rec.boxes:
            bid, cls = int(bid), int(cls)
            gid = group[bid] if cls == VEHICLE else group.get(owner.get(bid), 0)
            attrs = {"label": LABEL_OF_CLASS[cls], "source": "auto", "occluded": "0", "xtl": f"{x1:.2f}",
                     "ytl": f"{y1:.2f}", "xbr": f"{x2:.2f}", "ybr": f"{y2:.2f}", "z_order": "0"}
            if gid:
                attrs["group_id"] = str(gid)
            box = ET.SubElement(el, "box", attrs)
            if cls == WHEEL:
                ET.SubElement(box, "attribute", name="role").text = role.get(bid) or "none"
                ET.SubElement(box, "attribute", name="couple").text = str(number.get(bid, 0))
    ET.indent(root)
    notes = []
    if lost:
        notes.append(f"{lost} vehicles have one rear and one front wheel that are not a couple: CVAT reads them "
                     f"back as a couple (the roles give it)")
    if cross:
        notes.append(f"{cross} couples of wheels of different vehicles cannot be written in CVAT (groups)")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n", notes
