"""COCO detection JSON in: ``images``, ``annotations`` (``bbox`` [x, y, w, h] in pixels, ``category_id``) and
``categories`` named ``vehicle`` / ``wheel``.

COCO has no relations; each wheel annotation names its owner in ``attributes`` (where CVAT's COCO export puts a
shape's attributes) or as a top-level key: ``owner`` (the vehicle's annotation id; absent, empty or -1: none, and
0 when no annotation of the image has id 0, CVAT's default for a number attribute), ``role`` (``front``/``rear``)
and an optional ``couple`` number (as in CVAT: the two wheels of one vehicle with the same n > 0 form a couple).
``iscrowd: 1`` annotations become ignore regions. Per image, optional ``camera``, ``frame_id``, ``scene``.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from deepword.labelling.build import (
    CLASS_LABELS,
    RawBox,
    RawImage,
    RawLink,
    numbered_couples,
    parse_couple_number,
    parse_role,
    to_number,
)
from deepword.labelling.label_studio import load_json
from deepword.labelling.problems import LabellingError, Problems


def _attr(ann: dict, key: str):
    attrs = ann.get("attributes")
    if isinstance(attrs, dict) and key in attrs:
        return attrs[key], f"attributes.{key}"
    return ann.get(key), key


def read_coco(path: Path, problems: Problems) -> tuple[list[RawImage], list[str]]:
    doc = load_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("images"), list) or not isinstance(doc.get("annotations"), list):
        raise LabellingError(f"{path}: not a COCO detection file (a JSON object with 'images' and 'annotations')")
    categories = {}
    for c in doc.get("categories", []):
        if isinstance(c, dict) and "id" in c:
            categories[c["id"]] = str(c.get("name", ""))
    by_image: dict[object, list[dict]] = defaultdict(list)
    for k, ann in enumerate(doc["annotations"]):
        if not isinstance(ann, dict) or "image_id" not in ann:
            problems.add(f"annotation #{k + 1}", "image_id", "missing")
            continue
        by_image[ann["image_id"]].append(ann)
    images, known = [], set()
    for k, im in enumerate(doc["images"]):
        if not isinstance(im, dict) or "id" not in im or not im.get("file_name"):
            problems.add(f"image #{k + 1}", "file_name" if isinstance(im, dict) and "id" in im else "id", "missing")
            continue
        known.add(im["id"])
        where = f"image {im['file_name']!r}"
        img = RawImage(where=where, name=im["file_name"], name_field="file_name", camera=im.get("camera"),
                       scene=str(im.get("scene", "")))
        for fld in ("width", "height"):
            if im.get(fld) is not None:
                value = to_number(im[fld], where, fld, problems)
                setattr(img, fld, int(value) if value is not None else None)
        if im.get("frame_id") is not None:
            fid = to_number(im["frame_id"], where, "frame_id", problems)
            img.frame_id = int(fid) if fid is not None else None
        _read_annotations(img, by_image.get(im["id"], []), categories, problems)
        images.append(img)
    for image_id, anns in by_image.items():
        if image_id not in known:
            problems.add(f"annotation {anns[0].get('id')}", "image_id", f"image {image_id!r} is not in 'images'")
    return images, []


def _read_annotations(img: RawImage, anns: list[dict], categories: dict, problems: Problems) -> None:
    ids = {str(a.get("id")) for a in anns}
    owned: list[tuple[RawBox, str, object, str | None, str]] = []
    numbered = []
    for k, ann in enumerate(anns):
        aid = ann.get("id")
        where = f"{img.where}, annotation {aid}"
        if aid is None:
            problems.add(f"{img.where}, annotation #{k + 1}", "id", "missing")
            continue
        if ann.get("category_id") not in categories:
            problems.add(where, "category_id", f"unknown category_id {ann.get('category_id')!r}")
            continue
        label = categories[ann["category_id"]]
        bbox = ann.get("bbox")
        if not isinstance(bbox, list) or len(bbox) != 4:
            problems.add(where, "bbox", f"must be [x, y, width, height], got {bbox!r}")
            continue
        nums = [to_number(v, where, f"bbox[{i}]", problems) for i, v in enumerate(bbox)]
        if any(n is None for n in nums):
            continue
        x, y, w, h = nums
        if ann.get("iscrowd"):
            cls = CLASS_LABELS.get(label.strip().lower())
            if cls is None:
                problems.add(where, "category_id", f"unknown label {label!r} (expected vehicle or wheel)")
            else:
                img.ignore.append((x, y, x + w, y + h, cls))
            continue
        owner, owner_field = _attr(ann, "owner")
        role_value, role_field = _attr(ann, "role")
        couple_value, couple_field = _attr(ann, "couple")
        ok_role, role = parse_role(role_value, where, role_field, problems)
        couple = parse_couple_number(couple_value, where, couple_field, problems)
        if not ok_role or couple is None:
            continue
        box = RawBox(key=str(aid), where=where, label=label, label_field="category_id",
                     coords=(x, y, x + w, y + h), coord_fields=("bbox[0]", "bbox[1]", "bbox[2]", "bbox[3]"))
        img.boxes.append(box)
        if isinstance(owner, float) and owner.is_integer():
            owner = int(owner)
        if label.strip().lower() != "wheel":
            if couple:
                problems.add(where, couple_field, "a couple number belongs to a wheel, not a vehicle")
            if role is not None:
                problems.add(where, role_field, "a role belongs to a wheel, not a vehicle")
            if owner not in (None, "", -1, "-1") and not (str(owner) == "0" and "0" not in ids):
                problems.add(where, owner_field, "only a wheel has an owner")
            continue
        if owner in (None, "", -1, "-1") or (str(owner) == "0" and "0" not in ids):
            if role is not None:
                problems.add(where, role_field, f"role {role!r} given but the wheel has no owner")
            numbered.append((None, couple, box, couple_field))
            continue
        owned.append((box, str(owner).strip(), role, owner_field))
        numbered.append((str(owner).strip(), couple, box, couple_field))
    for box, owner, role, fld in owned:
        img.links.append(RawLink(box.key, owner, role, box.where, fld, owner_only=True))
    numbered_couples(img, numbered, problems)
