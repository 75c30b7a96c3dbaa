"""``export_labels``: WORD-format predictions (``deepword infer``'s ``labels.jsonl``) -> a file a labelling tool
opens with the model's boxes and relations as pre-annotations, for a team to correct instead of drawing."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from deepword.labelling.cvat import to_cvat
from deepword.labelling.label_studio import to_label_studio
from deepword.labelling.problems import LabellingError
from deepword.word_format import DatasetError, Record, read_records

TARGETS = ("label-studio", "cvat")


def read_predictions(pred: str | os.PathLike) -> list[Record]:
    try:
        return read_records(pred)
    except DatasetError as exc:
        raise LabellingError(str(exc)) from None


def export_labels(target: str, pred: str | os.PathLike, out: str | os.PathLike, model_version: str = "deepword",
                  image_root: str | None = None) -> tuple[int, list[str]]:
    """Write ``out`` for ``target`` (label-studio: a JSON list of tasks with ``predictions``; cvat: CVAT for images
    1.1 XML); returns (images written, notes on what the format cannot carry)."""
    if target not in TARGETS:
        raise LabellingError(f"unknown target {target!r} (one of {', '.join(TARGETS)})")
    records = read_predictions(pred)
    if target == "label-studio":
        tasks, notes = to_label_studio(records, model_version, image_root)
        text = json.dumps(tasks, indent=1) + "\n"
    else:
        text, notes = to_cvat(records)
        if image_root:
            notes.append("--image-root is for Label Studio; CVAT names images by their path in the task")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, out)
    return len(records), notes


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="deepword export-labels", description="Write WORD-format predictions as pre-annotations for a "
        "labelling tool, so that a team corrects the model's boxes and relations (docs/labelling.md).")
    p.add_argument("--to", dest="target", choices=TARGETS, required=True, help="the labelling tool")
    p.add_argument("--pred", type=Path, required=True, help="WORD-format predictions (deepword infer's labels.jsonl)")
    p.add_argument("--out", type=Path, required=True, help="the file to write (.json for Label Studio, .xml for CVAT)")
    p.add_argument("--model-version", default="deepword", help="Label Studio's model_version of the predictions")
    p.add_argument("--image-root", help="prefix of the image paths in Label Studio tasks, e.g. "
                   "'/data/local-files/?d=mydata/' or 'https://host/dataset/'")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        n, notes = export_labels(args.target, args.pred, args.out, args.model_version, args.image_root)
    except LabellingError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {n} images' predictions for {args.target} -> {args.out}")
    for note in notes:
        print(f"note: {note}")
    return 0
