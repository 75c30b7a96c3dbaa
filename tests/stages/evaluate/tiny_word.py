"""A tiny hand-built WORD-style dataset for stage tests: side views of parked cars in a row, nearer cars
lower and larger, so that wheels lie inside two vehicles' boxes as in the paper's Fig. 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.word_format import Record, difficulty_subsets, write_dataset_index, write_records

W, H = 160, 120


def car_row(rng: np.random.Generator, n_cars: int) -> tuple[np.ndarray, list, list]:
    """Boxes, relations and couples of ``n_cars`` side-view cars at random depths."""
    boxes, relations, pairs, bid = [], [], [], 0
    for _ in range(n_cars):
        s = rng.uniform(0.45, 1.0)                     # nearness: size and how low the car sits
        vw, vh = 90 * s, 38 * s
        bottom = 60 + 55 * s
        x1 = rng.uniform(-0.2 * vw, W - 0.8 * vw)
        v = [max(x1, 0), bottom - vh, min(x1 + vw, W), bottom]
        d = 0.42 * vh                                   # wheel diameter
        wheel_boxes = [[x1 + 0.12 * vw, bottom - d, x1 + 0.12 * vw + d, bottom],
                       [x1 + 0.88 * vw - d, bottom - d, x1 + 0.88 * vw, bottom]]
        vid = bid
        boxes.append(v + [1.0, 0, vid])
        bid += 1
        ids = []
        for wb in wheel_boxes:
            if wb[0] >= 0 and wb[2] <= W:
                boxes.append(wb + [1.0, 1, bid])
                relations.append((vid, bid, None))
                ids.append(bid)
                bid += 1
        if len(ids) == 2:
            pairs.append((ids[0], ids[1]))
    return np.array(boxes, dtype=np.float64), relations, pairs


def make_record(rng: np.random.Generator, frame: int, n_cars: int, camera: str = "left") -> Record:
    boxes, relations, pairs = car_row(rng, n_cars)
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
