"""``import_labels``: a tool's export + its images -> a validated WORD-style dataset directory (docs/design.md §4).

All or nothing: every problem is collected and reported together (``LabellingError``, one line each), and the
dataset is written only when there is none, into a temporary folder beside ``out`` that is read back with
``deepword.word_format`` (records and image headers) before it is renamed into place.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from deepword.labelling.build import ImageFinder, Summary, build_record, camera_of, frame_id_of, summarise
from deepword.labelling.coco import read_coco
from deepword.labelling.cvat import read_cvat
from deepword.labelling.label_studio import config as label_studio_config
from deepword.labelling.label_studio import read_label_studio
from deepword.labelling.problems import DEFAULT_LIMIT, LabellingError, Problems
from deepword.word_format import (
    CAMERAS,
    LABELS_FILE,
    DatasetError,
    Record,
    check_image_files,
    read_records,
    write_records,
)

READERS = {"label-studio": read_label_studio, "cvat": read_cvat, "coco": read_coco}
LINK_MODES = ("copy", "link")


@dataclass
class ImportResult:
    records: list[Record]
    summary: Summary
    out: Path


def convert(tool: str, export_file: str | os.PathLike, images_dir: str | os.PathLike, camera: str = "front",
            ) -> tuple[list[Record], dict[str, Path], Summary]:
    """The records an export describes, {record image path: source image file} and the summary, without writing
    anything; LabellingError with every problem found."""
    if tool not in READERS:
        raise LabellingError(f"unknown tool {tool!r} (one of {', '.join(READERS)})")
    if camera not in CAMERAS:
        raise LabellingError(f"--camera must be one of {', '.join(CAMERAS)}, got {camera!r}")
    export_file, images_dir = Path(export_file), Path(images_dir)
    if not export_file.is_file():
        raise LabellingError(f"{export_file}: file not found")
    if not images_dir.is_dir():
        raise LabellingError(f"{images_dir}: images folder not found")
    problems = Problems(str(export_file))
    raw_images, notes = READERS[tool](export_file, problems)
    finder = ImageFinder(images_dir)
    summary = Summary(notes=list(notes))
    records, sources, target_of = [], {}, {}
    for index, img in enumerate(raw_images):
        img.path, why = finder.find(img.name)
        if img.path is None:
            problems.add(img.where, img.name_field, why)
        cam = camera_of(img.camera, img.name, camera)
        if cam is None:
            problems.add(img.where, "camera", f"must be one of {', '.join(CAMERAS)}, got {img.camera!r}")
            continue
        if img.path is None:
            continue
        rel = f"images/{cam}/{img.path.name}"
        if rel in target_of:
            problems.add(img.where, img.name_field, f"{img.path.name} would be written to {rel} like "
                                                    f"{target_of[rel]} (same camera, same file name)")
            continue
        target_of[rel] = img.where
        rec = build_record(img, cam, frame_id_of(img.frame_id, img.name, index), rel, problems, summary)
        if rec is not None:
            records.append(rec)
            sources[rel] = img.path
    if problems:
        raise LabellingError(problems)
    if not records:
        # say why (e.g. tasks that hold only the model's predictions, not yet accepted or corrected)
        why = "".join(f"; {note}" for note in notes)
        raise LabellingError(f"{export_file}: no annotated images to import{why}")
    return records, sources, summarise(records, summary)


def write_dataset(records: list[Record], sources: dict[str, Path], out: str | os.PathLike, mode: str = "copy") -> Path:
    """Write ``out/labels.jsonl`` and ``out/images/<camera>/<name>`` (copied, or hard-linked with ``mode="link"``,
    copied where a link is not possible), check it by reading it back, and move it into place."""
    if mode not in LINK_MODES:
        raise LabellingError(f"unknown mode {mode!r} (copy or link)")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise LabellingError(f"{out}: already exists and is not empty; choose a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for rel, src in sources.items():
            dst = tmp / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            if mode == "link":
                try:
                    os.link(src, dst)
                    continue
                except OSError:
                    pass  # another file system, or links not allowed: copy
            shutil.copyfile(src, dst)
        write_records(tmp / LABELS_FILE, records)
        try:
            check_image_files(tmp, read_records(tmp / LABELS_FILE, root=tmp))
        except DatasetError as exc:  # a bug here, not in the input: the importer built a record the reader refuses
            raise LabellingError(f"the imported dataset does not read back: {exc}") from None
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def import_labels(tool: str, export_file: str | os.PathLike, images_dir: str | os.PathLike,
                  out: str | os.PathLike, camera: str = "front", mode: str = "copy") -> ImportResult:
    """Convert a Label Studio / CVAT / COCO export into a WORD-style dataset at ``out`` (see the module docstring)."""
    records, sources, summary = convert(tool, export_file, images_dir, camera)
    path = write_dataset(records, sources, out, mode)
    return ImportResult(records=records, summary=summary, out=path)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="deepword import", description="Import boxes and wheel-vehicle relations from a labelling tool's "
        "export into a validated WORD-style dataset (docs/labelling.md).")
    p.add_argument("file", nargs="?", type=Path, help="the tool's export (JSON or XML)")
    p.add_argument("--from", dest="tool", choices=tuple(READERS), help="the tool that wrote FILE")
    p.add_argument("--images", type=Path, help="folder holding the images the export names (searched recursively)")
    p.add_argument("--out", type=Path, help="the dataset folder to create (must not exist, or be empty)")
    p.add_argument("--camera", choices=CAMERAS, default="front",
                   help="camera of images without their own (a per-image field, or a camera-named folder)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--copy", dest="mode", action="store_const", const="copy", help="copy the images (default)")
    mode.add_argument("--link", dest="mode", action="store_const", const="link",
                      help="hard-link the images (copies where a link is not possible)")
    p.add_argument("--print-config", choices=("label-studio",),
                   help="print the labelling configuration for the tool and exit")
    p.add_argument("--max-problems", type=int, default=DEFAULT_LIMIT, help="problems printed (default %(default)s)")
    p.set_defaults(mode="copy")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.print_config:
        print(label_studio_config(), end="")
        return 0
    missing = [flag for flag, value in (("FILE", args.file), ("--from", args.tool), ("--images", args.images),
                                        ("--out", args.out)) if value is None]
    if missing:
        p.error(f"missing {', '.join(missing)}")
    try:
        result = import_labels(args.tool, args.file, args.images, args.out, args.camera, args.mode)
    except LabellingError as exc:
        print(f"error: {exc.count} problem{'s' if exc.count > 1 else ''} in {args.file}; nothing was written:",
              file=sys.stderr)
        for line in exc.lines(args.max_problems):
            print(f"  {line}", file=sys.stderr)
        return 2
    print(f"read {args.file} ({args.tool})")
    for line in result.summary.lines():
        print(f"  {line}")
    how = "hard-linked" if args.mode == "link" else "copied"
    print(f"wrote {result.out / LABELS_FILE} and {len(result.records)} images ({how}) under {result.out / 'images'}")
    return 0
