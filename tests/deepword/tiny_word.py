"""A tiny hand-built WORD-style dataset for stage tests: side views of parked cars in a row, nearer cars
lower and larger, so that wheels lie inside two vehicles' boxes as in the paper's Fig. 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepword.word_format import Record, difficulty_subsets, write_dataset_index, write_records
from tests.car_rows import CarRows

W, H = 160, 120


SCENES = CarRows(W, H, car=(90, 38), nearness=(0.45, 1.0), bottom=(60, 55), overhang=0.2, wheel_inset=0.12,
                 roles=False)


def make_record(rng: np.random.Generator, frame: int, n_cars: int, camera: str = "left") -> Record:
    boxes, relations, pairs = SCENES.car_row(rng, n_cars)
    return Record(image=f"images/{camera}/{frame:05d}.png", frame_id=frame, camera=camera, width=W, height=H,
                  boxes=boxes, relations=relations, wheel_pairs=pairs, scene="parking")


def write_png(path: Path) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.full((H, W, 3), 90, dtype=np.uint8)
    cv2.imwrite(str(path), img)


def build(out_dir: Path, n_train: int = 40, n_test: int = 16, seed: int = 0) -> Path:
    """Write labels, PNGs, dataset.json and splits.json; return the data-stage-like directory."""
    rng = np.random.default_rng(seed)
    records = [make_record(rng, i, int(rng.integers(1, 7))) for i in range(n_train + n_test)]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_records(out_dir / "labels.jsonl", records)
    for r in records:
        write_png(out_dir / r.image)
    images = [r.image for r in records]
    splits = {"train": images[:n_train], "val": [], "test": images[n_train:]}
    splits.update(difficulty_subsets(records[n_train:], seed))
    write_dataset_index(out_dir, out_dir, splits)
    return out_dir
