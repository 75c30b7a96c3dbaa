"""A tiny, valid WORD-style dataset that runs through the whole pipeline in seconds, including the edge
cases real data has and the generator never keeps: images without vehicles, without wheels, without any
box, and a wheel without an owner.

Each frame has four cameras: ``front`` four vehicles with two wheels each (a "hard" image), ``left`` one
vehicle with its wheels plus an ownerless wheel, ``right`` vehicles without wheels, ``rear`` wheels
without vehicles (even frames) or nothing at all (odd frames).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from deepword.word_format import VEHICLE, WHEEL, Record, write_records

W, H = 160, 120
VEHICLE_W, VEHICLE_H, WHEEL_PX = 36, 26, 9


class _Builder:
    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.img = (rng.normal(110, 12, (H, W, 3))).clip(0, 255).astype(np.uint8)
        self.boxes: list[list[float]] = []
        self.relations: list[tuple[int, int, str | None]] = []
        self.pairs: list[tuple[int, int]] = []

    def box(self, x1, y1, x2, y2, cls, colour) -> int:
        bid = len(self.boxes)
        self.boxes.append([float(x1), float(y1), float(x2), float(y2), 1.0, cls, bid])
        cv2.rectangle(self.img, (int(x1), int(y1)), (int(x2) - 1, int(y2) - 1), colour, -1)
        return bid

    def vehicle(self, x, y, wheels: bool) -> None:
        colour = tuple(int(c) for c in self.rng.integers(120, 255, 3))
        v = self.box(x, y, x + VEHICLE_W, y + VEHICLE_H, VEHICLE, colour)
        if wheels:
            wy = y + VEHICLE_H - WHEEL_PX
            rear = self.wheel(x + 2, wy)
            front = self.wheel(x + VEHICLE_W - 2 - WHEEL_PX, wy)
            self.relations += [(v, rear, "rear"), (v, front, "front")]
            self.pairs.append((rear, front))

    def wheel(self, x, y) -> int:
        return self.box(x, y, x + WHEEL_PX, y + WHEEL_PX, WHEEL, (20, 20, 20))


def _image(kind: str, rng: np.random.Generator) -> _Builder:
    b = _Builder(rng)
    if kind == "front":
        for i in range(4):
            b.vehicle(2 + i * 39, 20 + 50 * (i % 2), wheels=True)
    elif kind == "left":
        b.vehicle(30, 40, wheels=True)
        b.wheel(120, 100)  # lying on the road: no owner
    elif kind == "right":
        b.vehicle(10, 20, wheels=False)
        b.vehicle(90, 60, wheels=False)
    elif kind == "rear_wheels":
        b.wheel(20, 90)
        b.wheel(60, 95)
    return b


def write_tiny_dataset(root: Path, frames: int = 6, seed: int = 0) -> Path:
    """Write ``frames`` x 4 images and ``labels.jsonl`` under ``root``; returns ``root``."""
    rng = np.random.default_rng(seed)
    records = []
    for f in range(frames):
        for camera, kind in (("front", "front"), ("left", "left"), ("right", "right"),
                             ("rear", "rear_wheels" if f % 2 == 0 else "empty")):
            b = _image(kind, rng)
            rel = f"images/{camera}/{f:06d}.png"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / rel), cv2.cvtColor(b.img, cv2.COLOR_RGB2BGR))
            boxes = np.array(b.boxes, dtype=np.float64).reshape(-1, 7)
            records.append(Record(image=rel, frame_id=f, camera=camera, width=W, height=H, boxes=boxes,
                                  relations=b.relations, wheel_pairs=b.pairs, scene="parking"))
    write_records(root / "labels.jsonl", records)
    return root
