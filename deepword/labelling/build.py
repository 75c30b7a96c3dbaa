"""From what an annotation tool exported to WORD records (docs/design.md §4), tool-independent.

Each tool's reader (``label_studio``, ``cvat``, ``coco``) turns its file into ``RawImage``s: boxes in the tool's
own coordinates, keyed by the tool's own ids, and links between them. ``build_records`` checks them all,
collecting every problem, and assembles the records:

- a link between a wheel and a vehicle is ownership, its label (``front``/``rear``, or none) the wheel's role;
  a wheel has at most one owner;
- a link labelled ``couple`` between two wheels states a front/rear couple explicitly (the rear wheel is the one
  whose role is ``rear``; without roles, the link's first end);
- couples (``wheel_pairs``) otherwise come from the roles: a vehicle with exactly one ``rear`` and one ``front``
  wheel gives the couple (rear, front). A vehicle any of whose wheels carries an explicit couple statement takes
  exactly the couples stated (that is how a vehicle with both sides' wheels in view says which go together).
"""

from __future__ import annotations

import math
import re
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlparse

import numpy as np

from deepword.labelling.problems import Problems
from deepword.word_format import CAMERAS, ROLES, VEHICLE, WHEEL, Record, image_size

CLASS_LABELS = {"vehicle": VEHICLE, "wheel": WHEEL}
LABEL_OF_CLASS = {v: k for k, v in CLASS_LABELS.items()}
COUPLE = "couple"
LINK_LABELS = (*ROLES, COUPLE)  # the relation labels the importers accept
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
TOLERANCE_PX = 1.0  # a box may overshoot the image by this much (rounding); it is clipped


@dataclass
class RawBox:
    key: str                 # the tool's id of the box (region id, annotation id, box index)
    where: str               # how an error names it: "task 12, region 'abc'"
    label: str               # the class label as written in the export
    label_field: str
    coords: tuple            # x1, y1, x2, y2 in pixels, or x, y, w, h in percent (``percent``)
    coord_fields: tuple[str, str, str, str]
    percent: bool = False
    score: float = 1.0
    couple_given: bool = False  # the tool states this wheel's couples explicitly (see the module docstring)


@dataclass
class RawLink:
    a: str                   # box keys; for ownership either order, for a couple the first is the rear wheel
    b: str
    label: str | None        # "front" / "rear" (a wheel's role), "couple", or None
    where: str
    field: str
    owner_only: bool = False  # an ownership statement (a wheel's owner attribute), never a couple


@dataclass
class RawImage:
    where: str               # "task 12", "image 'a.png'"
    name: str                # the image as the export names it (path or URL)
    name_field: str
    path: Path | None = None  # the file found under --images
    width: int | None = None  # as the export claims (None: take the file's)
    height: int | None = None
    size_fields: tuple[str, str] = ("width", "height")
    camera: str | None = None  # a per-image camera field, if the tool has one
    frame_id: int | None = None
    scene: str = ""
    boxes: list[RawBox] = field(default_factory=list)
    links: list[RawLink] = field(default_factory=list)
    ignore: list[tuple[float, float, float, float, int]] = field(default_factory=list)


@dataclass
class Summary:
    """What an import read, for the one-screen report."""

    images: int = 0
    vehicles: int = 0
    wheels: int = 0
    owned: int = 0
    unowned: int = 0
    without_role: int = 0
    couples: int = 0
    explicit_couples: int = 0
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"images:   {self.images}", f"vehicles: {self.vehicles}",
               f"wheels:   {self.wheels} ({self.owned} owned, {self.unowned} without a vehicle; "
               f"{self.without_role} owned without a front/rear role)",
               f"couples:  {self.couples} wheel pairs ({self.explicit_couples} stated, "
               f"{self.couples - self.explicit_couples} from the roles)"]
        return out + [f"note: {n}" for n in self.notes]


class ImageFinder:
    """Finds the file an export names under the --images folder: by its path (or the longest tail of it), else by
    its file name (unique), else by the name without Label Studio's upload prefix (``1a2b3c4d-``)."""

    _UPLOAD_PREFIX = re.compile(r"^[0-9a-f]{8}-(.+)$")

    def __init__(self, images_dir: str | Path):
        self.root = Path(images_dir)
        self.by_name: dict[str, list[Path]] = defaultdict(list)
        if self.root.is_dir():
            for p in sorted(self.root.rglob("*")):
                if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file():
                    self.by_name[p.name].append(p)

    @staticmethod
    def relative_name(name: str) -> str:
        """The path part of an image reference: a plain path, a URL, or Label Studio's ``/data/local-files/?d=``."""
        parsed = urlparse(name)
        query = parse_qs(parsed.query)
        if "d" in query:
            return unquote(query["d"][0])
        return unquote(parsed.path) if parsed.scheme or parsed.query else name

    def find(self, name: str) -> tuple[Path | None, str]:
        """(the file, "") or (None, why not)."""
        rel = self.relative_name(name).replace("\\", "/")
        parts = [p for p in rel.split("/") if p not in ("", ".", "..")]
        if not parts:
            return None, f"no image file name in {name!r}"
        for i in range(len(parts) - 1):  # the longest tail of the path that exists under --images
            candidate = self.root.joinpath(*parts[i:])
            if candidate.is_file():
                return candidate, ""
        base = parts[-1]
        found = self.by_name.get(base, [])
        if not found and (m := self._UPLOAD_PREFIX.match(base)):
            found = self.by_name.get(m.group(1), [])
        if len(found) == 1:
            return found[0], ""
        if len(found) > 1:
            shown = ", ".join(str(p.relative_to(self.root)) for p in found[:3])
            return None, f"image {base!r} is ambiguous under {self.root}: {shown}"
        return None, f"image file {base!r} not found under {self.root}"


def parse_role(value, where: str, fld: str, problems: Problems) -> tuple[bool, str | None]:
    """(ok, role) of a role attribute: "front", "rear", or empty (no role)."""
    if value is None:
        return True, None
    text = str(value).strip().lower()
    if text in ("", "none"):
        return True, None
    if text not in ROLES:
        problems.add(where, fld, f"unknown role {value!r} (expected one of {', '.join(ROLES)}, or none)")
        return False, None
    return True, text


def to_number(value, where: str, fld: str, problems: Problems) -> float | None:
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if isinstance(value, bool) or not math.isfinite(x):
        problems.add(where, fld, f"must be a finite number, got {value!r}")
        return None
    return x


def frame_id_of(explicit, name: str, index: int) -> int:
    """A per-image frame field, else the digits of the file name (``000042.png`` -> 42), else the image's index."""
    if explicit is not None:
        return int(explicit)
    stem = Path(ImageFinder.relative_name(name)).stem
    return int(stem) if stem.isdigit() else index


def camera_of(explicit: str | None, name: str, default: str) -> str | None:
    """A per-image camera field, else a camera-named folder in the image's path (``front/000042.png``), else
    ``default``. None when the per-image field is not a camera name."""
    if explicit is not None:
        return explicit if explicit in CAMERAS else None
    parents = Path(ImageFinder.relative_name(name)).parent.parts
    for part in reversed(parents):
        if part in CAMERAS:
            return part
    return default


def _check_box(box: RawBox, width: int, height: int, problems: Problems) -> tuple[float, float, float, float] | None:
    a, b, c, d = box.coords
    if box.percent:
        x1, y1, x2, y2 = a / 100 * width, b / 100 * height, (a + c) / 100 * width, (b + d) / 100 * height
    else:
        x1, y1, x2, y2 = a, b, c, d
    fx1, fy1, fx2, fy2 = box.coord_fields  # percent: x, y, width, height
    ok = True
    if not x1 < x2:
        problems.add(box.where, fx2, f"empty box: x1={x1:.1f} x2={x2:.1f} (x1 < x2 required)")
        ok = False
    if not y1 < y2:
        problems.add(box.where, fy2, f"empty box: y1={y1:.1f} y2={y2:.1f} (y1 < y2 required)")
        ok = False
    size = f"the {width}x{height} image"
    for value, limit, fld, axis in ((x1, 0, fx1, "x1"), (y1, 0, fy1, "y1")):
        if value < limit - TOLERANCE_PX:
            problems.add(box.where, fld, f"box outside the image: {axis}={value:.1f} < 0 ({size})")
            ok = False
    for value, limit, fld, axis in ((x2, width, fx2, "x2"), (y2, height, fy2, "y2")):
        if value > limit + TOLERANCE_PX:
            problems.add(box.where, fld, f"box outside the image: {axis}={value:.1f} > {limit} ({size})")
            ok = False
    if not ok:
        return None
    return (min(max(x1, 0.0), width), min(max(y1, 0.0), height), min(max(x2, 0.0), width), min(max(y2, 0.0), height))


def _image_size(img: RawImage, problems: Problems) -> tuple[int, int] | None:
    """The image's real size (its header), checked against the size the export claims."""
    if img.path is None:
        if img.width and img.height:
            return img.width, img.height
        return None
    try:
        real = image_size(img.path)
    except (OSError, ValueError) as exc:
        problems.add(img.where, img.name_field, f"image file {img.path} cannot be read: {exc}")
        return None
    for claimed, actual, fld in ((img.width, real[0], img.size_fields[0]), (img.height, real[1], img.size_fields[1])):
        if claimed is not None and claimed != actual:
            problems.add(img.where, fld, f"the export says {img.width}x{img.height}, the image file "
                                         f"{img.path.name} is {real[0]}x{real[1]}")
            return None
    return real


def build_record(img: RawImage, camera: str, frame_id: int, image_rel: str, problems: Problems,
                 summary: Summary | None = None) -> Record | None:
    """One record from one tool image, or None with its problems added."""
    start = len(problems)
    size = _image_size(img, problems)
    if size is None:
        return None
    width, height = size
    keys = [b.key for b in img.boxes]
    dup = [k for k, n in Counter(keys).items() if n > 1]
    for k in dup:
        problems.add(img.where, "id", f"box id {k!r} is used by {Counter(keys)[k]} boxes")
    numeric = all(k.isdigit() for k in keys) and not dup
    ids = {b.key: (int(b.key) if numeric else i) for i, b in enumerate(img.boxes)}
    cls_of: dict[str, int] = {}
    rows = []
    for box in img.boxes:
        cls = CLASS_LABELS.get(str(box.label).strip().lower())
        if cls is None:
            problems.add(box.where, box.label_field, f"unknown label {box.label!r} (expected vehicle or wheel)")
            continue
        xyxy = _check_box(box, width, height, problems)
        if xyxy is None:
            continue
        if not 0.0 <= box.score <= 1.0:
            problems.add(box.where, "score", f"score must be in [0, 1], got {box.score}")
            continue
        cls_of[box.key] = cls
        rows.append([*xyxy, box.score, cls, ids[box.key]])
    relations, stated = _links(img, cls_of, ids, problems)
    if len(problems) > start:
        return None
    pairs = _couples(img, relations, stated, ids, problems)
    if len(problems) > start:
        return None
    if summary is not None:
        summary.explicit_couples += len(stated)
    boxes = np.array(sorted(rows, key=lambda r: r[6]), dtype=np.float64).reshape(-1, 7)
    ignore = np.array(img.ignore, dtype=np.float64).reshape(-1, 5)
    return Record(image=image_rel, frame_id=frame_id, camera=camera, width=width, height=height, boxes=boxes,
                  relations=sorted(relations), wheel_pairs=sorted(pairs), scene=img.scene, ignore=ignore)


def _links(img: RawImage, cls_of: dict[str, int], ids: dict[str, int], problems: Problems):
    """Ownership relations (vehicle id, wheel id, role) and stated couples (rear key, front key, link) of an image."""
    relations: list[tuple[int, int, str | None]] = []
    owner: dict[str, tuple[str, RawLink]] = {}
    couples: list[tuple[str, str, RawLink]] = []
    known = set(ids)
    for link in img.links:
        missing = [k for k in (link.a, link.b) if k not in known]
        if missing:
            problems.add(link.where, link.field, f"relation to a missing id {missing[0]!r}")
            continue
        if link.a not in cls_of or link.b not in cls_of:
            continue  # the box itself has a problem, reported already
        if link.label is not None and link.label not in LINK_LABELS:
            problems.add(link.where, link.field, f"unknown relation label {link.label!r} "
                                                 f"(expected one of {', '.join(LINK_LABELS)}, or none)")
            continue
        kinds = {cls_of[link.a], cls_of[link.b]}
        ends = f"{link.a!r} and {link.b!r}"
        if kinds == {VEHICLE}:
            problems.add(link.where, link.field, f"relation between two vehicles ({ends})")
        elif kinds == {WHEEL}:
            if link.owner_only:
                problems.add(link.where, link.field, f"relation between two wheels ({ends}): an owner must be a vehicle")
            elif link.label in ROLES:
                problems.add(link.where, link.field, f"relation between two wheels ({ends}) labelled "
                                                     f"{link.label!r}: a role links a wheel to its vehicle; "
                                                     f"two wheels link only as a {COUPLE!r}")
            elif link.a == link.b:
                problems.add(link.where, link.field, f"a wheel cannot form a couple with itself ({link.a!r})")
            else:
                couples.append((link.a, link.b, link))
        elif link.label == COUPLE:
            problems.add(link.where, link.field, f"a {COUPLE!r} links two wheels, not a wheel and a vehicle ({ends})")
        else:
            wheel, vehicle = (link.a, link.b) if cls_of[link.a] == WHEEL else (link.b, link.a)
            if wheel in owner:
                first = owner[wheel][0]
                what = "twice" if first == vehicle else f"to {first!r} and {vehicle!r}"
                problems.add(link.where, link.field, f"wheel {wheel!r} has two owners: it is related {what}")
                continue
            owner[wheel] = (vehicle, link)
            relations.append((ids[vehicle], ids[wheel], link.label))
    return relations, couples


def _couples(img: RawImage, relations, explicit, ids: dict[str, int], problems: Problems) -> list[tuple[int, int]]:
    """wheel_pairs: the stated couples, and for each vehicle without a stated couple its one rear + one front."""
    key_of = {v: k for k, v in ids.items()}
    role_of = {w: r for _, w, r in relations}
    owner_of = {w: v for v, w, _ in relations}
    stated = {b.key for b in img.boxes if b.couple_given}
    pairs: list[tuple[int, int]] = []
    in_pair: dict[int, str] = {}
    for a, b, link in explicit:
        ia, ib = ids[a], ids[b]
        stated |= {a, b}
        ra, rb = role_of.get(ia), role_of.get(ib)
        if ra is not None and ra == rb:
            problems.add(link.where, link.field, f"couple of two {ra} wheels ({a!r} and {b!r}): a couple is a "
                                                 f"rear and a front wheel")
            continue
        rear, front = (ib, ia) if (ra == "front" or rb == "rear") else (ia, ib)
        for w in (ia, ib):
            if w in in_pair:
                problems.add(link.where, link.field, f"wheel {key_of[w]!r} is in two couples "
                                                     f"(also with {in_pair[w]!r})")
        in_pair[ia], in_pair[ib] = b, a
        pairs.append((rear, front))
    explicit_vehicles = {owner_of[ids[k]] for k in stated if ids[k] in owner_of}
    wheels_of: dict[int, list[int]] = defaultdict(list)
    for v, w, _ in relations:
        wheels_of[v].append(w)
    for v, wheels in wheels_of.items():
        if v in explicit_vehicles:
            continue
        rear = [w for w in wheels if role_of[w] == "rear"]
        front = [w for w in wheels if role_of[w] == "front"]
        if len(rear) == 1 and len(front) == 1:
            pairs.append((rear[0], front[0]))
    return pairs


def derived_pairs(rec: Record) -> dict[int, set[tuple[int, int]]]:
    """{vehicle: the couple the roles alone give it} (the rule above), for the exporters."""
    out: dict[int, set[tuple[int, int]]] = {}
    wheels_of: dict[int, list[tuple[int, str | None]]] = defaultdict(list)
    for v, w, r in rec.relations:
        wheels_of[v].append((w, r))
    for v, wheels in wheels_of.items():
        rear = [w for w, r in wheels if r == "rear"]
        front = [w for w, r in wheels if r == "front"]
        out[v] = {(rear[0], front[0])} if len(rear) == 1 and len(front) == 1 else set()
    return out


def explicit_pairs(rec: Record) -> tuple[set[tuple[int, int]], int]:
    """The couples an export must state (the rest follow from the roles), and how many vehicles' lack of a couple
    cannot be written (their one rear and one front wheel would read back as a couple)."""
    owner = rec.owner_of()
    derived = derived_pairs(rec)
    per_vehicle: dict[int, set] = {v: set() for v in derived}
    loose = set()
    for a, b in rec.wheel_pairs:
        va, vb = owner.get(a), owner.get(b)
        if va is not None and va == vb:
            per_vehicle[va].add((a, b))
        else:
            loose.add((a, b))
    stating = {v for v, ps in per_vehicle.items() if ps and ps != derived[v]}
    stating |= {owner[w] for p in loose for w in p if w in owner}
    lost = sum(1 for v, ps in per_vehicle.items() if not ps and derived[v] and v not in stating)
    stated = loose | {p for v in stating for p in per_vehicle.get(v, set())}
    return stated, lost


def summarise(records: list[Record], summary: Summary) -> Summary:
    for rec in records:
        owners = rec.owner_of()
        wheels = set(rec.box_ids[rec.class_ids == WHEEL].tolist())
        summary.images += 1
        summary.vehicles += rec.n_vehicles
        summary.wheels += len(wheels)
        summary.owned += len(wheels & set(owners))
        summary.unowned += len(wheels - set(owners))
        summary.without_role += sum(1 for _, _, r in rec.relations if r is None)
        summary.couples += len(rec.wheel_pairs)
    return summary


def numbered_couples(img: RawImage, numbered: list[tuple[object, int, RawBox, str]], problems: Problems) -> None:
    """CVAT's and COCO's ``couple`` attribute: within one vehicle (``scope``: its group or owner; None for wheels
    without one), the two wheels with the same number n > 0 form a couple (0: not stated). Adds the links to
    ``img`` and marks the wheels as stating their couples."""
    buckets: dict[tuple[object, int], list[tuple[RawBox, str]]] = defaultdict(list)
    for scope, number, box, fld in numbered:
        if number > 0:
            buckets[(scope, number)].append((box, fld))
            box.couple_given = True
    for (_, number), members in buckets.items():
        box, fld = members[0]
        if len(members) != 2:
            names = ", ".join(repr(b.key) for b, _ in members)
            problems.add(box.where, fld, f"couple {number} has {len(members)} wheels ({names}); a couple is two wheels")
            continue
        img.links.append(RawLink(members[0][0].key, members[1][0].key, COUPLE, box.where, fld))


def parse_couple_number(value, where: str, fld: str, problems: Problems) -> int | None:
    if value is None or (isinstance(value, str) and not value.strip()):
        return 0
    x = to_number(value, where, fld, problems)
    if x is None:
        return None
    if x < 0 or not float(x).is_integer():
        problems.add(where, fld, f"must be a whole number >= 0 (0: no stated couple), got {value!r}")
        return None
    return int(x)
