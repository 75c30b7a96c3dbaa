"""The WORD-style dataset format of DESIGN §4: the one reader, writer and validator every stage uses.

A dataset is ``<root>/labels.jsonl`` (one record per image) plus the image files the records name.
The data stage's output directory additionally holds ``dataset.json`` (where the root is) and
``splits.json`` (train/val/test and the easy/hard/mixed test subsets, as lists of image paths).
"""

from __future__ import annotations

import json
import math
import os
import random
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

VEHICLE = 0
WHEEL = 1
CAMERAS = ("front", "left", "right", "rear")
ROLES = ("front", "rear")
SPLITS = ("train", "val", "test")
SUBSETS = ("easy", "hard", "mixed")
LABELS_FILE = "labels.jsonl"
REQUIRED_KEYS = ("image", "frame_id", "camera", "width", "height", "boxes", "relations")


class DatasetError(ValueError):
    """A problem in a dataset, located by file, line (1-based) and field."""

    def __init__(self, file: str | os.PathLike, line: int | None, field: str, message: str):
        self.file, self.line, self.field, self.message = str(file), line, field, message
        where = f"{self.file}:{line}" if line is not None else self.file
        super().__init__(f"{where}: field '{field}': {message}")


@dataclass
class Record:
    """One image's annotations. ``boxes`` is an (N, 7) float array: x1, y1, x2, y2, score, class_id, box_id."""

    image: str
    frame_id: int
    camera: str
    width: int
    height: int
    boxes: np.ndarray
    relations: list[tuple[int, int, str | None]]
    wheel_pairs: list[tuple[int, int]]
    scene: str = ""
    extra: dict = field(default_factory=dict)
    source: tuple[str, int] | None = None  # (file, line) the record was read from, for error messages

    @property
    def xyxy(self) -> np.ndarray:
        return self.boxes[:, :4]

    @property
    def scores(self) -> np.ndarray:
        return self.boxes[:, 4]

    @property
    def class_ids(self) -> np.ndarray:
        return self.boxes[:, 5].astype(int)

    @property
    def box_ids(self) -> np.ndarray:
        return self.boxes[:, 6].astype(int)

    @property
    def n_vehicles(self) -> int:
        return int((self.class_ids == VEHICLE).sum())

    @property
    def n_wheels(self) -> int:
        return int((self.class_ids == WHEEL).sum())

    def owner_of(self) -> dict[int, int]:
        """wheel box_id -> vehicle box_id for every related wheel."""
        return {w: v for v, w, _ in self.relations}

    def to_json(self) -> dict:
        boxes = [
            [round(float(x1), 2), round(float(y1), 2), round(float(x2), 2), round(float(y2), 2),
             round(float(s), 4), int(c), int(b)]
            for x1, y1, x2, y2, s, c, b in self.boxes
        ]
        relations = [[v, w, r] if r is not None else [v, w] for v, w, r in self.relations]
        out = {"image": self.image, "frame_id": self.frame_id, "camera": self.camera, "scene": self.scene,
               "width": self.width, "height": self.height, "boxes": boxes, "relations": relations,
               "wheel_pairs": [list(p) for p in self.wheel_pairs]}
        out.update(self.extra)
        return out


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
    image = obj["image"]
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
    if not _is_int(obj["frame_id"]):
        fail("frame_id", f"must be an integer, got {obj['frame_id']!r}")
    if obj["camera"] not in CAMERAS:
        fail("camera", f"must be one of {CAMERAS}, got {obj['camera']!r}")
    for key in ("width", "height"):
        if not _is_int(obj[key]) or obj[key] <= 0:
            fail(key, f"must be a positive integer, got {obj[key]!r}")
    width, height = int(obj["width"]), int(obj["height"])

    raw_boxes = obj["boxes"]
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
    cls_of = {int(b): int(c) for c, b in zip(boxes[:, 5], boxes[:, 6], strict=True)}

    raw_rel = obj["relations"]
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

    raw_pairs = obj.get("wheel_pairs", [])
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

    known = set(REQUIRED_KEYS) | {"scene", "wheel_pairs"}
    extra = {k: v for k, v in obj.items() if k not in known}
    scene = obj.get("scene", "")
    return Record(image=image, frame_id=int(obj["frame_id"]), camera=obj["camera"], width=width, height=height,
                  boxes=boxes, relations=relations, wheel_pairs=pairs, scene=str(scene), extra=extra,
                  source=(str(file), line if line is not None else 0))


def read_records(labels_path: str | os.PathLike, root: str | os.PathLike | None = None,
                 check_images: bool = False, allow_empty: bool = False) -> list[Record]:
    """Read and validate every line of a labels file. ``root`` (default: the file's folder) is what image
    paths must stay inside; ``check_images`` also requires every named image to exist, be a complete PNG/JPEG
    and have the record's size (header checks only, see ``check_image_file``)."""
    labels_path = Path(labels_path)
    root = Path(root) if root is not None else labels_path.parent
    if not labels_path.is_file():
        raise DatasetError(labels_path, None, "<file>", "labels file not found")
    records: list[Record] = []
    seen: dict[str, int] = {}
    try:
        fh = open(labels_path, "rb")  # bytes: a bad byte is reported with its line, not as a decode traceback
    except OSError as exc:
        raise DatasetError(labels_path, None, "<file>", f"cannot be read: {exc.strerror}") from None
    with fh:
        for lineno, raw in enumerate(fh, start=1):
            try:
                text = raw.decode("utf-8-sig" if lineno == 1 else "utf-8")
            except UnicodeDecodeError as exc:
                raise DatasetError(labels_path, lineno, "<encoding>", f"not UTF-8 (byte {exc.start + 1} of the line)") from None
            if not text.strip():
                continue
            try:
                obj = json.loads(text)
            except json.JSONDecodeError as exc:
                # exc.pos, not exc.colno: the line's own newline would make an error at its end read "column 1"
                raise DatasetError(labels_path, lineno, "<json>", f"malformed JSON: {exc.msg} at character {exc.pos + 1}") from None
            except RecursionError:
                raise DatasetError(labels_path, lineno, "<json>", "malformed JSON: nested too deeply") from None
            rec = parse_record(obj, str(labels_path), lineno, root=root)
            if rec.image in seen:
                raise DatasetError(labels_path, lineno, "image", f"{rec.image!r} already described on line {seen[rec.image]}")
            seen[rec.image] = lineno
            if check_images:
                check_image_file(root, rec)
            records.append(rec)
    if not records and not allow_empty:
        raise DatasetError(labels_path, None, "<file>", "no records: the dataset is empty")
    return records


def write_records(labels_path: str | os.PathLike, records: list[Record]) -> None:
    """Write records as JSON lines (atomically: a temporary file renamed into place)."""
    labels_path = Path(labels_path)
    tmp = labels_path.with_name(labels_path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        for rec in records:
            fh.write(json.dumps(rec.to_json(), separators=(",", ":")) + "\n")
    os.replace(tmp, labels_path)


def load_image(root: str | os.PathLike, record: Record) -> np.ndarray:
    """The record's image as an RGB uint8 array, checked against the record's width and height.
    The header check comes first because OpenCV decodes a truncated JPEG without complaint."""
    import cv2  # deferred: keeps the reader importable without OpenCV's load time

    check_image_file(root, record)
    path = Path(root) / record.image
    file, line = record.source or (str(path), None)
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(file, line, "image", f"image file {path} is corrupt or not an image")
    h, w = bgr.shape[:2]
    if (w, h) != (record.width, record.height):
        fld = "width" if w != record.width else "height"
        raise DatasetError(file, line, fld, f"image {path} is {w}x{h}, the record says {record.width}x{record.height}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


# --- cheap image checks: headers and trailers, no decoding -----------------------------------------------

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_TRAILER = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the empty IEND chunk every complete PNG ends with
_JPEG_SOI, _JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_TAIL = 1024  # the end-of-image marker must lie this close to the end (some writers pad after it)


def _jpeg_size(fh) -> tuple[int, int]:
    """Walk the JPEG marker segments up to the first start-of-frame and read its width and height."""
    fh.seek(2)
    while True:
        byte = fh.read(1)
        if byte != b"\xff":
            raise ValueError("JPEG marker expected: the file is corrupt or truncated")
        marker = fh.read(1)
        while marker == b"\xff":  # fill bytes
            marker = fh.read(1)
        if not marker:
            raise ValueError("JPEG header is truncated")
        m = marker[0]
        if m == 0x01 or 0xD0 <= m <= 0xD7:  # markers without a length field
            continue
        length_bytes = fh.read(2)
        if len(length_bytes) < 2:
            raise ValueError("JPEG header is truncated")
        length = int.from_bytes(length_bytes, "big")
        if m in _JPEG_SOF:
            sof = fh.read(5)
            if len(sof) < 5:
                raise ValueError("JPEG header is truncated")
            return int.from_bytes(sof[3:5], "big"), int.from_bytes(sof[1:3], "big")
        if m in (0xD9, 0xDA) or length < 2:
            raise ValueError("JPEG has no frame header before its image data")
        fh.seek(length - 2, os.SEEK_CUR)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG file from its header, and a check that the file is complete
    (PNG: ends with IEND; JPEG: an end-of-image marker in its last KiB). Reads a few hundred bytes, decodes
    nothing: cheap enough to check every image of a dataset up front. Raises ValueError saying what is wrong."""
    with open(path, "rb") as fh:
        head = fh.read(24)
        size = fh.seek(0, os.SEEK_END)
        if head.startswith(_PNG_SIGNATURE):
            if len(head) < 24 or head[12:16] != b"IHDR":
                raise ValueError("PNG header is truncated or corrupt")
            wh = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            fh.seek(max(size - len(_PNG_TRAILER), 0))
            if fh.read() != _PNG_TRAILER:
                raise ValueError("PNG is truncated (it does not end with an IEND chunk)")
        elif head.startswith(_JPEG_SOI):
            wh = _jpeg_size(fh)
            fh.seek(max(size - _JPEG_TAIL, 0))
            if _JPEG_EOI not in fh.read():
                raise ValueError("JPEG is truncated (no end-of-image marker at its end)")
        else:
            raise ValueError("not a PNG or JPEG file")
    if min(wh) <= 0:
        raise ValueError(f"header gives an empty image size {wh[0]}x{wh[1]}")
    return wh


def check_image_file(root: str | os.PathLike, record: Record) -> None:
    """Check that the record's image exists, is a complete PNG/JPEG and has the record's size, from its
    header only; raise DatasetError with the record's file and line."""
    path = Path(root) / record.image
    file, line = record.source or (str(path), None)
    if not path.is_file():
        raise DatasetError(file, line, "image", f"image file {path} not found")
    try:
        w, h = image_size(path)
    except OSError as exc:
        raise DatasetError(file, line, "image", f"image file {path} cannot be read: {exc.strerror}") from None
    except ValueError as exc:
        raise DatasetError(file, line, "image", f"image file {path}: {exc}") from None
    if (w, h) != (record.width, record.height):
        fld = "width" if w != record.width else "height"
        raise DatasetError(file, line, fld, f"image {path} is {w}x{h}, the record says {record.width}x{record.height}")


def check_image_files(root: str | os.PathLike, records: list[Record]) -> None:
    """check_image_file for every record, stopping at the first problem."""
    for rec in records:
        check_image_file(root, rec)


# --- splits (DESIGN §7) -------------------------------------------------------------------------------

def split_by_frame(records: list[Record], fractions: dict[str, float], seed: int) -> dict[str, list[str]]:
    """Assign whole frames (all cameras of one instant) to train/val/test; returns image paths per split."""
    frames = sorted({r.frame_id for r in records})
    random.Random(seed).shuffle(frames)
    total = sum(fractions[s] for s in SPLITS)
    n_val = round(len(frames) * fractions["val"] / total)
    n_test = round(len(frames) * fractions["test"] / total)
    if len(frames) >= 3:  # every split asked for gets a frame; a split of fraction 0 stays empty
        n_val = max(n_val, 1) if fractions["val"] > 0 else 0
        n_test = max(n_test, 1) if fractions["test"] > 0 else 0
    split_of = {}
    for i, f in enumerate(frames):
        split_of[f] = "test" if i < n_test else "val" if i < n_test + n_val else "train"
    return {s: [r.image for r in records if split_of[r.frame_id] == s] for s in SPLITS}


def difficulty_subsets(records: list[Record], seed: int, max_easy_vehicles: int = 3) -> dict[str, list[str]]:
    """easy: at most ``max_easy_vehicles`` annotated vehicles; hard: more; mixed: half easy, half hard
    (as many of each as the smaller kind has, halved, drawn with a fixed seed)."""
    easy = [r.image for r in records if r.n_vehicles <= max_easy_vehicles]
    hard = [r.image for r in records if r.n_vehicles > max_easy_vehicles]
    rng = random.Random(seed)
    half = max(min(len(easy), len(hard)) // 2, 1) if easy and hard else 0
    mixed = sorted(rng.sample(easy, half) + rng.sample(hard, half)) if half else sorted(easy or hard)
    return {"easy": easy, "hard": hard, "mixed": mixed}


@dataclass
class Dataset:
    """A validated dataset with its splits, as the data stage leaves it."""

    root: Path
    records: list[Record]
    splits: dict[str, list[str]]

    def subset(self, name: str) -> list[Record]:
        if name not in self.splits:
            raise KeyError(f"unknown split {name!r}; have {sorted(self.splits)}")
        by_image = {r.image: r for r in self.records}
        return [by_image[i] for i in self.splits[name]]


def write_dataset_index(out_dir: Path, root: Path, splits: dict[str, list[str]]) -> None:
    """Write the data stage's ``dataset.json`` (root of the images and labels) and ``splits.json``."""
    out_dir = Path(out_dir)
    rel = os.path.relpath(root, out_dir) if Path(root).resolve() == out_dir.resolve() else str(Path(root).resolve())
    (out_dir / "dataset.json").write_text(json.dumps({"root": rel, "labels": LABELS_FILE}, indent=1))
    (out_dir / "splits.json").write_text(json.dumps(splits))


def open_dataset(data_dir: str | os.PathLike) -> Dataset:
    """Open the data stage's output directory (``dataset.json`` + ``splits.json``)."""
    data_dir = Path(data_dir)
    index_path = data_dir / "dataset.json"
    try:
        index = json.loads(index_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(index_path, None, "<file>", f"not a data stage output: {exc}") from None
    root = (data_dir / index["root"]).resolve()
    records = read_records(root / index.get("labels", LABELS_FILE), root=root)
    splits = json.loads((data_dir / "splits.json").read_text())
    return Dataset(root=root, records=records, splits=splits)
