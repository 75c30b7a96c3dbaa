"""Tiny images and a WORD record with every kind of relation, for the labelling tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from deepword.word_format import LABELS_FILE, Record, write_records

W, H = 64, 48


def png(path: Path, width: int = W, height: int = H) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((height, width, 3), 90, np.uint8))
    return path


def word_record(frame_id: int = 42, camera: str = "front") -> Record:
    """Vehicle 0 with a rear and a front wheel (its couple follows from the roles) and a wheel without a role;
    vehicle 3 showing both sides (two couples that must be stated); wheel 8 without a vehicle."""
    boxes = [
        [2.0, 10.0, 30.0, 40.0, 1.0, 0, 0],
        [4.5, 30.0, 10.25, 38.0, 1.0, 1, 1],
        [22.0, 30.0, 28.0, 38.0, 1.0, 1, 2],
        [33.0, 5.0, 63.0, 40.0, 1.0, 0, 3],
        [34.0, 30.0, 38.0, 36.0, 1.0, 1, 4],
        [36.0, 33.0, 40.0, 39.0, 1.0, 1, 5],
        [55.0, 30.0, 59.0, 36.0, 1.0, 1, 6],
        [57.0, 33.0, 62.0, 39.0, 1.0, 1, 7],
        [10.0, 41.0, 14.0, 47.5, 1.0, 1, 8],
        [15.0, 33.0, 18.0, 38.0, 1.0, 1, 9],
    ]
    relations = [(0, 1, "rear"), (0, 2, "front"), (0, 9, None),
                 (3, 4, "rear"), (3, 5, "rear"), (3, 6, "front"), (3, 7, "front")]
    pairs = [(1, 2), (4, 6), (5, 7)]
    return Record(image=f"images/{camera}/{frame_id:06d}.png", frame_id=frame_id, camera=camera, width=W, height=H,
                  boxes=np.array(boxes, dtype=np.float64), relations=relations, wheel_pairs=pairs, scene="parking")


def word_dataset(root: Path, records: list[Record]) -> Path:
    for rec in records:
        png(root / rec.image, rec.width, rec.height)
    write_records(root / LABELS_FILE, records)
    return root / LABELS_FILE


def same_records(a: list[Record], b: list[Record], tol: float = 0.02) -> None:
    assert len(a) == len(b)
    for x, y in zip(sorted(a, key=lambda r: r.image), sorted(b, key=lambda r: r.image), strict=True):
        assert (x.image, x.frame_id, x.camera, x.width, x.height) == (y.image, y.frame_id, y.camera, y.width, y.height)
        assert x.boxes.shape == y.boxes.shape
        np.testing.assert_allclose(x.boxes[:, :4], y.boxes[:, :4], atol=tol)
        np.testing.assert_array_equal(x.boxes[:, 5:], y.boxes[:, 5:])
        assert sorted(x.relations, key=str) == sorted(y.relations, key=str)
        assert sorted(x.wheel_pairs) == sorted(y.wheel_pairs)
