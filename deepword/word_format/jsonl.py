"""Labels files: JSON lines in, validated records out, and back (atomically)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from deepword.word_format.images import check_image_file
from deepword.word_format.parse import parse_record
from deepword.word_format.record import DatasetError, Record


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
