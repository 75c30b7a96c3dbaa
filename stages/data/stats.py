"""Dataset statistics of docs/design.md §7 (``data.<split>.*`` metrics) and the splits both data sources share."""

from __future__ import annotations

import numpy as np

from deepword.geometry import containment
from deepword.word_format import SPLITS, VEHICLE, WHEEL, Record, difficulty_subsets, split_by_frame

WHOLLY_INSIDE = 0.99  # a wheel "inside" a vehicle box: at least this share of its area (Fig. 2's hard case)


def make_splits(records: list[Record], fractions: dict, seed: int, max_easy_vehicles: int) -> dict[str, list[str]]:
    """train/val/test by frame, plus easy/hard/mixed drawn from test."""
    splits = split_by_frame(records, dict(fractions), seed)
    by_image = {r.image: r for r in records}
    splits.update(difficulty_subsets([by_image[i] for i in splits["test"]], seed, max_easy_vehicles))
    return splits


def multi_box_wheels(rec: Record) -> int:
    """Number of wheels lying wholly inside more than one vehicle box."""
    cls = rec.class_ids
    wheels, vehicles = rec.xyxy[cls == WHEEL], rec.xyxy[cls == VEHICLE]
    if not len(wheels) or len(vehicles) < 2:
        return 0
    return int(((containment(wheels, vehicles) >= WHOLLY_INSIDE).sum(axis=1) > 1).sum())


def boxes_meet_at_wheel(rec: Record) -> bool:
    """Fig. 7's case: two vehicle boxes intersect, and the intersection overlaps a wheel box."""
    cls = rec.class_ids
    wheels, vehicles = rec.xyxy[cls == WHEEL], rec.xyxy[cls == VEHICLE]
    for i in range(len(vehicles)):
        for j in range(i + 1, len(vehicles)):
            lo = np.maximum(vehicles[i, :2], vehicles[j, :2])
            hi = np.minimum(vehicles[i, 2:], vehicles[j, 2:])
            if np.all(hi > lo):
                over = (np.minimum(wheels[:, 2:], hi) - np.maximum(wheels[:, :2], lo)).clip(0).prod(axis=1)
                if (over > 0).any():
                    return True
    return False


def split_metrics(records: list[Record], splits: dict[str, list[str]]) -> dict[str, float]:
    by_image = {r.image: r for r in records}
    out: dict[str, float] = {}
    for split in SPLITS:
        recs = [by_image[i] for i in splits[split]]
        n = len(recs)
        wheels = sum(r.n_wheels for r in recs)
        out[f"data.{split}.images"] = float(n)
        out[f"data.{split}.vehicles_per_image"] = sum(r.n_vehicles for r in recs) / max(n, 1)
        out[f"data.{split}.wheels_per_image"] = wheels / max(n, 1)
        out[f"data.{split}.multi_box_wheel_share"] = 100.0 * sum(multi_box_wheels(r) for r in recs) / max(wheels, 1)
    out["data.test.easy_images"] = float(len(splits["easy"]))
    out["data.test.hard_images"] = float(len(splits["hard"]))
    return out
