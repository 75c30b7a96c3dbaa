"""Build the bad-input corpus: one tiny WORD-style dataset (docs/design.md §4) per fault.

Each case is a directory ``corpus/<case>/`` with ``labels.jsonl``, its images and ``expected.json``: the
line and field a reader must name and a fragment of its message. Every case has a valid record on line 1
and (unless the whole file is the problem) the faulty one on line 2, so a reader that reports the wrong
line is caught. Images are 16x12 PNGs stored uncompressed (zlib level 0), so the bytes are the same on
every machine and the committed corpus can be checked against this script.

    .venv/bin/python tests/reliability/make_corpus.py            # rewrites tests/reliability/corpus/
    .venv/bin/python -m pipeline data=word data.root=tests/reliability/corpus/box_x2_lt_x1   # see one
"""

from __future__ import annotations

import json
import shutil
import struct
import sys
import zlib
from collections.abc import Callable
from pathlib import Path

W, H = 16, 12
CORPUS = Path(__file__).resolve().parent / "corpus"


def png_bytes(width: int, height: int, seed: int) -> bytes:
    """A deterministic RGB PNG (a colour gradient shifted by ``seed``)."""
    rows = bytearray()
    for y in range(height):
        rows.append(0)  # filter type 0 for each scanline
        for x in range(width):
            rows += bytes(((x * 16 + seed * 40) % 256, (y * 20) % 256, (seed * 70 + x * y) % 256))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(rows), 0))
            + chunk(b"IEND", b""))


def valid_record(i: int, camera: str) -> dict:
    """One vehicle (box 0) with its rear (1) and front (2) wheel."""
    return {"image": f"images/{camera}/{i:06d}.png", "frame_id": i, "camera": camera, "scene": "parking",
            "width": W, "height": H,
            "boxes": [[1, 1, 15, 11, 1.0, 0, 0], [2, 8, 5, 11, 1.0, 1, 1], [11, 8, 14, 11, 1.0, 1, 2]],
            "relations": [[0, 1, "rear"], [0, 2, "front"]], "wheel_pairs": [[1, 2]]}


class Dataset:
    """A corpus case under construction: two valid records with their images, then one fault applied."""

    def __init__(self):
        self.records = [valid_record(0, "front"), valid_record(1, "left")]
        self.images = {r["image"]: png_bytes(W, H, i) for i, r in enumerate(self.records)}
        self.labels_text: str | None = None  # when set, written instead of the records (raw faults)
        self.outside: dict[str, bytes] = {}  # files written next to the case directory

    @property
    def bad(self) -> dict:
        return self.records[1]

    def labels(self) -> bytes:
        if self.labels_text is not None:
            return self.labels_text.encode("utf-8", errors="surrogateescape")
        return "".join(json.dumps(r) + "\n" for r in self.records).encode()


def _set(path: list, value) -> Callable[[Dataset], None]:
    def apply(ds: Dataset) -> None:
        target = ds.bad
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value
    return apply


def _malformed_json(ds):
    text = json.dumps(ds.records[0]) + "\n" + json.dumps(ds.bad)[:-2] + "\n"
    ds.labels_text = text


def _not_utf8(ds):
    ds.labels_text = json.dumps(ds.records[0]) + "\n" + json.dumps(ds.bad).replace("parking", "park\udcffing") + "\n"


def _missing_key(ds):
    del ds.bad["boxes"]


def _two_owners(ds):
    ds.bad["boxes"].append([0, 0, 8, 12, 1.0, 0, 3])
    ds.bad["relations"].append([3, 2])


def _missing_image(ds):
    del ds.images[ds.bad["image"]]


def _corrupt_image(ds):
    ds.images[ds.bad["image"]] = b"this is a text file, not an image\n"


def _corrupt_pixels(ds):
    """Header and trailer intact, pixel data garbage: only decoding finds it."""
    good = ds.images[ds.bad["image"]]
    start = good.index(b"IDAT") + 4
    ds.images[ds.bad["image"]] = good[:start] + bytes(0xA5 for _ in range(40)) + good[start + 40:]


def _truncated_image(ds):
    good = ds.images[ds.bad["image"]]
    ds.images[ds.bad["image"]] = good[: len(good) // 2]


def _wrong_size(ds):
    ds.images[ds.bad["image"]] = png_bytes(W + 4, H, 1)


def _dotdot(ds):
    ds.bad["image"] = "../_outside.png"
    ds.outside["_outside.png"] = png_bytes(W, H, 9)  # it exists: refused for where it is, not for being absent


def _absolute(ds):
    ds.bad["image"] = "/etc/passwd"


def _empty(ds):
    ds.labels_text = "\n\n"


def _duplicate_image(ds):
    ds.bad["image"] = ds.records[0]["image"]


def _huge_integer(ds):
    ds.labels_text = json.dumps(ds.records[0]) + "\n" + json.dumps(ds.bad).replace("[11, 8, 14, 11", "[11, 8, 1" + "0" * 400 + ", 11") + "\n"


# name -> (fault, line, field, message fragment, what finds it: "labels" = reading labels.jsonl,
#          "files" = header checks of read_records(check_images=True), "decode" = load_image only)
CASES: dict[str, tuple[Callable[[Dataset], None], int | None, str, str, str]] = {
    "malformed_json": (_malformed_json, 2, "<json>", "malformed JSON", "labels"),
    "not_utf8": (_not_utf8, 2, "<encoding>", "not UTF-8", "labels"),
    "missing_key": (_missing_key, 2, "boxes", "missing", "labels"),
    "box_x2_lt_x1": (_set(["boxes", 1, 2], 1.0), 2, "boxes[1]", "x1 < x2", "labels"),
    "box_nan": (_set(["boxes", 0, 1], float("nan")), 2, "boxes[0]", "finite", "labels"),
    "box_huge_integer": (_huge_integer, 2, "boxes[2]", "finite", "labels"),
    "box_outside_image": (_set(["boxes", 0, 2], W + 30), 2, "boxes[0]", "outside", "labels"),
    "unknown_class": (_set(["boxes", 2, 5], 7), 2, "boxes[2]", "unknown class_id", "labels"),
    "duplicate_box_id": (_set(["boxes", 2, 6], 1), 2, "boxes[2]", "duplicate box_id", "labels"),
    "relation_to_missing_box": (_set(["relations", 1, 1], 9), 2, "relations[1]", "does not exist", "labels"),
    "relation_between_wheels": (_set(["relations", 1], [1, 2]), 2, "relations[1]", "not a vehicle", "labels"),
    "wheel_with_two_owners": (_two_owners, 2, "relations[2]", "already has owner", "labels"),
    "bad_wheel_pair": (_set(["wheel_pairs", 0], [0, 2]), 2, "wheel_pairs[0]", "not an existing wheel", "labels"),
    "non_integer_frame_id": (_set(["frame_id"], "one"), 2, "frame_id", "integer", "labels"),
    "fractional_frame_id": (_set(["frame_id"], 1.5), 2, "frame_id", "integer", "labels"),
    "unknown_camera": (_set(["camera"], "fisheye_top"), 2, "camera", "must be one of", "labels"),
    "path_outside_root_dotdot": (_dotdot, 2, "image", "leaves the dataset root", "labels"),
    "path_outside_root_absolute": (_absolute, 2, "image", "leaves the dataset root", "labels"),
    "duplicate_image": (_duplicate_image, 2, "image", "already described on line 1", "labels"),
    "empty_dataset": (_empty, None, "<file>", "empty", "labels"),
    "missing_image": (_missing_image, 2, "image", "not found", "files"),
    "corrupt_image": (_corrupt_image, 2, "image", "not a PNG or JPEG", "files"),
    "truncated_image": (_truncated_image, 2, "image", "truncated", "files"),
    "wrong_image_size": (_wrong_size, 2, "width", "is 20x12, the record says 16x12", "files"),
    "corrupt_pixel_data": (_corrupt_pixels, 2, "image", "corrupt", "decode"),
}


def write_dataset(ds: Dataset, case: Path) -> Path:
    (case / "images").mkdir(parents=True)
    (case / "labels.jsonl").write_bytes(ds.labels())
    for rel, data in ds.images.items():
        (case / rel).parent.mkdir(parents=True, exist_ok=True)
        (case / rel).write_bytes(data)
    for rel, data in ds.outside.items():
        (case.parent / rel).write_bytes(data)
    return case


def build_case(name: str, corpus: Path) -> Path:
    fault, line, fld, message, found_by = CASES[name]
    ds = Dataset()
    fault(ds)
    case = write_dataset(ds, corpus / name)
    expected = {"line": line, "field": fld, "message": message, "found_by": found_by}
    (case / "expected.json").write_text(json.dumps(expected, indent=1) + "\n")
    return case


def build_corpus(corpus: Path = CORPUS) -> list[Path]:
    if corpus.exists():
        shutil.rmtree(corpus)
    corpus.mkdir(parents=True)
    return [build_case(name, corpus) for name in CASES]


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else CORPUS
    print(f"wrote {len(build_corpus(out))} cases under {out}")
