"""The data stage's output directory: ``dataset.json`` (where the labels and images are) and ``splits.json``
(image paths per split and test subset), and the ``Dataset`` it opens as."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from deepword.word_format.jsonl import read_records
from deepword.word_format.record import LABELS_FILE, DatasetError, Record


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
