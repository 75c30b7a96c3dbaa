"""What the detector still misses: recall of ground-truth boxes by size, occlusion and image-border truncation.

AP says how good a detector is; this says where to look next. A ground-truth box counts as found when a
detection of its class with score >= ``min_score`` matches it at IoU >= 0.5 (``deepword.metrics.match_boxes``,
greedy by score, the evaluation's own matching). Groups, per class:

- ``size``: the box's shorter side in original-image pixels (< 8, 8-16, 16-32, 32-64, >= 64);
- ``occluded`` (vehicles): at least ``occluded_share`` of the box lies inside another vehicle's box (parked
  rows, jams);
- ``border``: the box touches the image border (truncated by the fisheye's field of view or the frame).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from deepword.geometry import pairwise_intersection
from deepword.metrics import match_boxes
from deepword.word_format import VEHICLE, Record

SIZE_EDGES = (0.0, 8.0, 16.0, 32.0, 64.0, math.inf)


def size_label(low: float, high: float) -> str:
    return f"<{high:g}" if low == 0 else (f">={low:g}" if math.isinf(high) else f"{low:g}-{high:g}")


def found_flags(truth: Record, prediction: Record, min_score: float) -> np.ndarray:
    """(N,) bool: which of ``truth``'s boxes a detection with score >= ``min_score`` matches."""
    # filtered here rather than with the runtime's keep_at: importing stages.inference would put the relation's
    # code into the detector stage's cache key
    kept = dataclasses.replace(prediction, boxes=prediction.boxes[prediction.scores >= min_score])
    matched = set(match_boxes(truth, kept).values())
    return np.array([int(b) in matched for b in truth.box_ids], dtype=bool)


def box_groups(truth: Record, occluded_share: float = 0.3, border_px: float = 1.0) -> dict[str, np.ndarray]:
    """Per box: ``shorter`` side (px), ``occluded`` (covered by another vehicle box), ``border`` (touches it)."""
    xyxy = truth.xyxy
    sides = xyxy[:, 2:] - xyxy[:, :2]
    area = np.maximum(sides[:, 0] * sides[:, 1], 1e-9)
    vehicles = truth.class_ids == VEHICLE
    inter = pairwise_intersection(xyxy, xyxy)
    np.fill_diagonal(inter, 0.0)
    covered = (inter[:, vehicles].max(axis=1) if vehicles.any() else np.zeros(len(xyxy))) / area
    border = ((xyxy[:, 0] <= border_px) | (xyxy[:, 1] <= border_px) | (xyxy[:, 2] >= truth.width - border_px)
              | (xyxy[:, 3] >= truth.height - border_px))
    return {"shorter": sides.min(axis=1), "occluded": covered >= occluded_share, "border": border}


def recall_breakdown(truths: Sequence[Record], predictions: Sequence[Record], class_names: Sequence[str],
                     min_score: float, occluded_share: float = 0.3) -> list[dict]:
    """Rows ``{class, group, boxes, found, recall}`` (recall in percent, NaN for an empty group) over all images."""
    found, shorter, occluded, border, classes = [], [], [], [], []
    for truth, prediction in zip(truths, predictions, strict=True):
        if truth.image != prediction.image:
            raise ValueError(f"recall_breakdown: prediction for {prediction.image!r} paired with {truth.image!r}")
        if not len(truth.boxes):
            continue
        groups = box_groups(truth, occluded_share)
        found.append(found_flags(truth, prediction, min_score))
        shorter.append(groups["shorter"])
        occluded.append(groups["occluded"])
        border.append(groups["border"])
        classes.append(truth.class_ids.astype(int))
    if not found:
        return []
    found, shorter, occluded, border, classes = map(np.concatenate, (found, shorter, occluded, border, classes))
    rows = []
    for cls, name in enumerate(class_names):
        of_class = classes == cls
        selections = [(f"size {size_label(lo, hi)} px", (shorter >= lo) & (shorter < hi))
                      for lo, hi in zip(SIZE_EDGES[:-1], SIZE_EDGES[1:], strict=True)]
        if cls == VEHICLE:  # a wheel always lies inside its own vehicle's box: occlusion is a vehicle's group
            selections += [("occluded", occluded), ("not occluded", ~occluded)]
        selections += [("at the border", border), ("all", np.ones_like(border))]
        for group, selected in selections:
            chosen = of_class & selected
            n, k = int(chosen.sum()), int(found[chosen].sum())
            rows.append({"class": name, "group": group, "boxes": n, "found": k,
                         "recall": 100.0 * k / n if n else math.nan})
    return rows


def breakdown_metrics(rows: list[dict], split: str) -> dict[str, float]:
    """``detector.<split>.recall.<class>.<group>`` for the non-empty groups (names with spaces as _)."""
    def key(group: str) -> str:
        return group.replace(" px", "").replace(" ", "_").replace(">=", "ge").replace("<", "lt")

    return {f"detector.{split}.recall.{r['class']}.{key(r['group'])}": r["recall"] for r in rows if r["boxes"]}


def write_breakdown(path: str | Path, rows: list[dict], min_score: float, split: str) -> None:
    """The breakdown as a Markdown table: one row per group, one column pair per class."""
    classes = list(dict.fromkeys(r["class"] for r in rows))
    groups = list(dict.fromkeys(r["group"] for r in rows))
    cell = {(r["class"], r["group"]): r for r in rows}
    lines = [f"# What the detector misses ({split} split)", "",
             f"Recall at IoU >= 0.5 of detections with score >= {min_score:g}, by ground-truth group "
             "(size = shorter box side in image pixels; occluded = at least 30 % inside another vehicle's box).", "",
             "| group | " + " | ".join(f"{c} boxes | {c} recall" for c in classes) + " |",
             "|---|" + "---:|---:|" * len(classes)]
    for group in groups:
        parts = []
        for c in classes:
            r = cell.get((c, group), {"boxes": 0})
            parts += [str(r["boxes"]), "–" if not r["boxes"] else f"{r['recall']:.1f} %"]
        lines.append(f"| {group} | " + " | ".join(parts) + " |")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text("\n".join(lines) + "\n")
