"""The ``data`` stage: generate (``data=synword``) or validate (``data=word``) a WORD-style dataset, split it
by frame into train/val/test with easy/hard/mixed test subsets, and report docs/design.md §7's dataset metrics.
The ``shift_data`` stage builds the cross-domain benchmark's held-out test set (``shift.data``, a
data-like config drawing only held-out families) the same way; its metrics are ``data.shift.test.*``.

A data config with ``sources`` composes several (``data=adapt``: the generator's data and N images of a new
domain's pool, docs/adapt.md; ``stages.data.compose``).

Output directory: ``dataset.json`` (where the labels and images are), ``splits.json``, and for synthetic
data ``labels.jsonl`` + ``images/``; ``artifacts/contact_sheet.png`` shows a few frames with their labels.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from deepword.word_format import LABELS_FILE, DatasetError, read_records, write_dataset_index, write_records
from stages.data.compose import build_sources
from stages.data.show import frame_sheet
from stages.data.stats import make_splits, split_metrics
from stages.data.synword import generate

SHEET_FRAMES = 3


def run(cfg, inputs: dict, out_dir: Path) -> dict[str, float]:
    return build_dataset(OmegaConf.to_container(cfg.data, resolve=True), int(cfg.seed), Path(out_dir))


def run_heldout(cfg, inputs: dict, out_dir: Path) -> dict[str, float]:
    """The held-out test set of the cross-domain benchmark; only its test split is reported."""
    metrics = build_dataset(OmegaConf.to_container(cfg.shift.data, resolve=True), int(cfg.seed), Path(out_dir))
    return {k.replace("data.", "data.shift.", 1): v for k, v in metrics.items() if k.startswith("data.test.")}


def build_dataset(dcfg: dict, seed: int, out_dir: Path) -> dict[str, float]:
    if dcfg.get("sources") is not None:   # several sources in one dataset (data=adapt): stages.data.compose

        records, splits, metrics = build_sources(dcfg, seed, out_dir)
        write_dataset_index(out_dir, out_dir, splits)
        (out_dir / "artifacts").mkdir(exist_ok=True)
        for name in dcfg["sources"]:   # a sheet per source: the first frames of each
            own = [r for r in records if r.extra.get("data_source") == name]
            if own:
                frame_sheet(out_dir, own, SHEET_FRAMES, out_dir / "artifacts" / f"contact_sheet_{name}.png")
        return metrics
    if dcfg["name"] == "synword":

        records = generate(dcfg, seed, out_dir, workers=dcfg.get("workers"))
        if not records:
            raise DatasetError(out_dir / LABELS_FILE, None, "<file>", "the generator kept no image (none had a relation)")
        write_records(out_dir / LABELS_FILE, records)
        root = out_dir
    elif dcfg["name"] == "word":
        root = Path(dcfg["root"]).expanduser().resolve()
        records = read_records(root / LABELS_FILE, root=root, check_images=True)
    else:
        raise ValueError(f"unknown data source {dcfg['name']!r} (data=synword or data=word)")
    splits = make_splits(records, dcfg["split"], seed, int(dcfg["max_easy_vehicles"]))
    write_dataset_index(out_dir, root, splits)
    (out_dir / "artifacts").mkdir(exist_ok=True)
    frame_sheet(root, records, SHEET_FRAMES, out_dir / "artifacts" / "contact_sheet.png")
    return split_metrics(records, splits)
