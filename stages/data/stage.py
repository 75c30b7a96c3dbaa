"""The ``data`` stage: generate (``data=synword``) or validate (``data=word``) a WORD-style dataset, split it
by frame into train/val/test with easy/hard/mixed test subsets, and report docs/design.md §7's dataset metrics.

Output directory: ``dataset.json`` (where the labels and images are), ``splits.json``, and for synthetic
data ``labels.jsonl`` + ``images/``; ``artifacts/contact_sheet.png`` shows a few frames with their labels.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from stages.data.show import frame_sheet
from stages.data.stats import make_splits, split_metrics
from stages.word_format import LABELS_FILE, DatasetError, read_records, write_dataset_index, write_records

SHEET_FRAMES = 3


def run(cfg, inputs: dict, out_dir: Path) -> dict[str, float]:
    dcfg = OmegaConf.to_container(cfg.data, resolve=True)
    out_dir = Path(out_dir)
    if dcfg["name"] == "synword":
        from stages.data.synword import generate

        records = generate(dcfg, int(cfg.seed), out_dir, workers=dcfg.get("workers"))
        if not records:
            raise DatasetError(out_dir / LABELS_FILE, None, "<file>", "the generator kept no image (none had a relation)")
        write_records(out_dir / LABELS_FILE, records)
        root = out_dir
    elif dcfg["name"] == "word":
        root = Path(dcfg["root"]).expanduser().resolve()
        records = read_records(root / LABELS_FILE, root=root, check_images=True)
    else:
        raise ValueError(f"unknown data source {dcfg['name']!r} (data=synword or data=word)")
    splits = make_splits(records, dcfg["split"], int(cfg.seed), int(dcfg["max_easy_vehicles"]))
    write_dataset_index(out_dir, root, splits)
    (out_dir / "artifacts").mkdir(exist_ok=True)
    frame_sheet(root, records, SHEET_FRAMES, out_dir / "artifacts" / "contact_sheet.png")
    return split_metrics(records, splits)
