"""A tiny hand-built WORD dataset (flat-coloured "vehicles" standing on two dark "wheels") for detector tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from deepword.word_format import CAMERAS, Record, split_by_frame, write_dataset_index, write_records


def toy_record(frame_id: int, camera: str, width: int, height: int, rng: np.random.Generator) -> tuple[Record, np.ndarray]:
    image = np.full((height, width, 3), 90, dtype=np.uint8)
    image += rng.integers(0, 20, size=image.shape, dtype=np.uint8)
    boxes, relations, pairs = [], [], []
    n_vehicles = 1 + frame_id % 2
    for v in range(n_vehicles):
        w, h = int(rng.integers(width // 4, width // 3)), int(rng.integers(height // 5, height // 3))
        x1 = int(v * width / n_vehicles + rng.integers(2, width / n_vehicles - w - 2))
        y1 = int(rng.integers(2, height - h - 8))
        colour = tuple(int(c) for c in rng.integers(120, 255, size=3))
        cv2.rectangle(image, (x1, y1), (x1 + w, y1 + h), colour, -1)
        vid = len(boxes)
        boxes.append([x1, y1, x1 + w, y1 + h + 4, 1.0, 0, vid])
        r = max(3, h // 5)
        wheel_ids = []
        for cx in (x1 + r + 1, x1 + w - r - 1):
            cy = y1 + h
            cv2.circle(image, (cx, cy), r, (20, 20, 20), -1)
            wid = len(boxes)
            boxes.append([cx - r, cy - r, cx + r, cy + r, 1.0, 1, wid])
            wheel_ids.append(wid)
        relations += [(vid, wheel_ids[0], "rear"), (vid, wheel_ids[1], "front")]
        pairs.append((wheel_ids[0], wheel_ids[1]))
    image_path = f"images/{camera}/{frame_id:06d}.png"
    record = Record(image=image_path, frame_id=frame_id, camera=camera, width=width, height=height,
                    boxes=np.array(boxes, dtype=np.float64), relations=relations, wheel_pairs=pairs, scene="toy")
    return record, image


def make_toy_dataset(root: Path, n_frames: int = 6, width: int = 128, height: int = 96, seed: int = 0) -> Path:
    """Write ``n_frames`` x 2 cameras of toy images + labels + splits into ``root``; returns ``root``."""
    rng = np.random.default_rng(seed)
    records = []
    for frame in range(n_frames):
        for camera in CAMERAS[:2]:
            record, image = toy_record(frame, camera, width, height, rng)
            path = root / record.image
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            records.append(record)
    write_records(root / "labels.jsonl", records)
    write_dataset_index(root, root, split_by_frame(records, {"train": 0.6, "val": 0.2, "test": 0.2}, seed))
    return root


@pytest.fixture(scope="session")
def toy_dataset(tmp_path_factory) -> Path:
    return make_toy_dataset(tmp_path_factory.mktemp("toy_word"))


@pytest.fixture(autouse=True)
def _one_thread():
    # The test machine's two cores are shared; one intra-op thread keeps runs predictable.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
