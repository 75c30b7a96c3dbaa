"""Where a detector's AP@0.5 goes: its false positives by kind, and the AP each kind costs.

AP@0.5 falls short of 100 for two reasons: ground truth that no detection finds (recall) and detections that
find nothing (precision). This splits the second by kind, after TIDE (Bolya et al., ECCV 2020), and answers
"what would the AP be without them" with the project's one AP (``deepword.detection.average_precision``) run on a changed
detection list, so each figure is exactly the AP of a detector that never made that kind of error:

- ``background``: IoU < 0.1 with every ground-truth box of its class;
- ``duplicate``: IoU >= 0.5 with a ground-truth box that a higher-scoring detection already found;
- ``loose``: IoU 0.1-0.5 with a ground-truth box of its class: found, but placed too loosely to count.
  Its oracle places it *on* the box it overlaps most when no detection found that box (TIDE's localisation
  fix), and removes it otherwise.

Without any false positive the AP is bounded by recall alone: ``max_recall`` is the share of the evaluated
ground truth that some detection (any kept score) matches at IoU 0.5. Detections are matched as in the AP:
per class, greedily by score, to evaluated ground truth first; one on an ignored box (shorter side under
``min_box_px``; an "ignore" region there) or in one of the record's ignore regions is neither kind and stays.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from deepword.detection.average_precision import coco_average_precision
from deepword.geometry import pairwise_intersection, pairwise_iou
from deepword.metrics import match_boxes
from deepword.word_format import Record

KINDS = ("background", "duplicate", "loose")
# what each oracle does, in the order of the report: (metric name, row label, kinds removed, loose ones placed)
FIXES = (("no_background", "without background boxes", ("background",), False),
         ("no_duplicates", "without duplicates", ("duplicate",), False),
         ("loose_placed", "loose boxes placed on their ground truth", (), True),
         ("no_false_positives", "without any false positive", KINDS, False))
LOOSE_IOU = 0.1
MATCH_IOU = 0.5


@dataclasses.dataclass
class ImageErrors:
    """One image's detections classified: ``kind[i]`` is ``"tp"``, ``"ignored"`` or one of ``KINDS``;
    ``place_on[i]`` the ground-truth row a loose detection would be placed on (-1: none free)."""
    kind: list[str]
    place_on: np.ndarray
    found: dict[int, int]      # per class: evaluated ground-truth boxes some detection matches
    evaluated: dict[int, int]  # per class: evaluated ground-truth boxes


def classify(truth: Record, prediction: Record, min_box_px: float) -> ImageErrors:
    """Classify ``prediction``'s detections against ``truth`` (see the module doc)."""
    n = len(prediction.boxes)
    kind, place_on = ["tp"] * n, np.full(n, -1)
    sides = (truth.xyxy[:, 2:] - truth.xyxy[:, :2]).min(axis=1) if len(truth.boxes) else np.zeros(0)
    evaluated_gt = sides >= min_box_px
    # the evaluation's own matching (per class, greedily by score, IoU >= 0.5) against the evaluated boxes only
    to_gt = match_boxes(dataclasses.replace(truth, boxes=truth.boxes[evaluated_gt]), prediction, MATCH_IOU)
    row_of_id = {int(b): k for k, b in enumerate(truth.box_ids)}
    taken = {row_of_id[g] for g in to_gt.values()}  # rows of the ground truth some detection found
    found, evaluated = {}, {}
    for cls in np.unique(np.concatenate([truth.class_ids, prediction.class_ids])).astype(int):
        dets = np.flatnonzero(prediction.class_ids == cls)
        gts = np.flatnonzero((truth.class_ids == cls) & evaluated_gt)
        ignored = truth.xyxy[(truth.class_ids == cls) & ~evaluated_gt]
        ignored = np.concatenate([ignored, truth.ignore[truth.ignore[:, 4].astype(int) == cls, :4]])
        found[int(cls)], evaluated[int(cls)] = sum(int(g) in taken for g in gts), len(gts)
        iou = pairwise_iou(prediction.xyxy[dets], truth.xyxy[gts]) if len(gts) else np.zeros((len(dets), 0))
        # an ignore region absorbs a detection mostly inside it, as COCO's crowd regions (deepword.detection.average_precision)
        det_area = np.maximum(np.prod(prediction.xyxy[dets, 2:] - prediction.xyxy[dets, :2], axis=1), 1e-9)
        inside_ignored = (pairwise_intersection(prediction.xyxy[dets], ignored).max(axis=1) / det_area
                          if len(ignored) else np.zeros(len(dets)))
        # the greedy order: a loose detection is placed on a box only if no higher-scoring detection took it
        rank = np.empty(len(dets), dtype=int)
        rank[np.argsort(-prediction.scores[dets], kind="stable")] = np.arange(len(dets))
        taken_at = {row_of_id[to_gt[int(prediction.box_ids[i])]]: rank[row] for row, i in enumerate(dets)
                    if int(prediction.box_ids[i]) in to_gt}
        for row, i in enumerate(dets):
            if int(prediction.box_ids[i]) in to_gt:
                continue
            if inside_ignored[row] >= MATCH_IOU:
                kind[i] = "ignored"
                continue
            best = float(iou[row].max()) if len(gts) else 0.0
            if best >= MATCH_IOU:
                kind[i] = "duplicate"
            elif best >= LOOSE_IOU:
                kind[i] = "loose"
                target = int(gts[int(np.argmax(iou[row]))])
                if taken_at.get(target, len(dets)) > rank[row]:
                    place_on[i] = target
            else:
                kind[i] = "background"
    return ImageErrors(kind=kind, place_on=place_on, found=found, evaluated=evaluated)


def _fixed(prediction: Record, errors: ImageErrors, truth: Record, removed: Sequence[str], place: bool) -> Record:
    """``prediction`` without the detections of the ``removed`` kinds; with ``place``, each loose detection moved
    onto its ground-truth box where that box is free (the first by score wins it) and removed otherwise."""
    boxes = prediction.boxes.copy()
    keep = np.array([k not in removed for k in errors.kind], dtype=bool)
    if place:
        placed: set[int] = set()
        for i in np.argsort(-prediction.scores, kind="stable"):
            if errors.kind[i] != "loose":
                continue
            target = int(errors.place_on[i])
            if target >= 0 and target not in placed:
                placed.add(target)
                boxes[i, :4] = truth.boxes[target, :4]
            else:
                keep[i] = False
    return dataclasses.replace(prediction, boxes=boxes[keep].reshape(-1, boxes.shape[1]))


def ap_error_breakdown(truths: Sequence[Record], predictions: Sequence[Record], class_names: Sequence[str],
                       min_box_px: float) -> dict[str, dict[str, float]]:
    """Per class: ``ap50`` and ``ap`` (AP@[.5:.95]) as reported, ``max_recall``, the count of each kind of false positive
    (``n_<kind>``) and ``ap50_<fix>`` for every oracle of ``FIXES`` (percent)."""
    truths, predictions = list(truths), list(predictions)
    for truth, prediction in zip(truths, predictions, strict=True):
        if truth.image != prediction.image:
            raise ValueError(f"ap_error_breakdown: prediction for {prediction.image!r} paired with {truth.image!r}")
    errors = [classify(t, p, min_box_px) for t, p in zip(truths, predictions, strict=True)]
    out = {name: {} for name in class_names}

    def average_precision(preds: list[Record]) -> dict[str, dict[str, float]]:
        return coco_average_precision(preds, truths, tuple(class_names), min_box_px)

    for name, ap in average_precision(predictions).items():
        out[name] |= {"ap50": ap["ap50"], "ap": ap["ap"]}
    for fix, _, removed, place in FIXES:
        fixed = average_precision([_fixed(p, e, t, removed, place)
                                   for t, p, e in zip(truths, predictions, errors, strict=True)])
        for name, ap in fixed.items():
            out[name][f"ap50_{fix}"] = ap["ap50"]
    for c, name in enumerate(class_names):
        found = evaluated = 0
        counts = dict.fromkeys(KINDS, 0)
        for prediction, e in zip(predictions, errors, strict=True):
            found, evaluated = found + e.found.get(c, 0), evaluated + e.evaluated.get(c, 0)
            for k, cls in zip(e.kind, prediction.class_ids, strict=True):
                if int(cls) == c and k in counts:
                    counts[k] += 1
        out[name]["max_recall"] = 100.0 * found / evaluated if evaluated else float("nan")
        out[name] |= {f"n_{k}": float(v) for k, v in counts.items()}
    return out


def error_metrics(breakdown: dict[str, dict[str, float]], split: str) -> dict[str, float]:
    """``detector.<split>.max_recall.<class>`` and ``detector.<split>.ap50_<fix>.<class>``."""
    return {f"detector.{split}.{key}.{name}": value for name, row in breakdown.items()
            for key, value in row.items() if key == "max_recall" or key.startswith("ap50_")}


def breakdown_markdown(breakdown: dict[str, dict[str, float]], images: str, min_box_px: float) -> str:
    """The breakdown as a Markdown section titled by which ``images`` it is of (``"test split"``): one row per
    oracle, one column pair per class."""
    names = list(breakdown)
    lines = [f"## Where AP@0.5 goes ({images})", "",
             "AP@0.5 if the detector had not made one kind of false positive, as TIDE (Bolya et al. 2020) measures it "
             f"(ground truth under {min_box_px:g} px ignored, as in the reported AP). Background: IoU < 0.1 with every "
             "box of its class; duplicate: a box another detection already found; loose: IoU 0.1-0.5 with a box. "
             "Without any false positive AP is bounded by recall: the last row is the share of the ground truth that "
             "some detection finds at IoU 0.5.", "",
             "| | " + " | ".join(f"{n} AP@0.5 | {n} detections" for n in names) + " |",
             "|---|" + "---:|---:|" * len(names)]

    def count(name: str, kinds: Sequence[str]) -> str:
        return str(int(sum(breakdown[name][f"n_{k}"] for k in kinds)))

    lines.append("| as is | " + " | ".join(f"{breakdown[n]['ap50']:.1f} | –" for n in names) + " |")
    for fix, label, removed, place in FIXES:
        kinds = ("loose",) if place else removed
        lines.append(f"| {label} | " + " | ".join(f"{breakdown[n][f'ap50_{fix}']:.1f} | {count(n, kinds)}"
                                                    for n in names) + " |")
    lines.append("| ground truth found at any score (max recall) | "
                 + " | ".join(f"{breakdown[n]['max_recall']:.1f} % | –" for n in names) + " |")
    return "\n".join(lines) + "\n"


def append_breakdown(path: str | Path, breakdown: dict[str, dict[str, float]], images: str, min_box_px: float) -> None:
    """Add the section to the end of ``path`` (the misses report)."""
    path = Path(path)
    text = path.read_text() if path.is_file() else ""
    path.write_text(text + ("\n" if text else "") + breakdown_markdown(breakdown, images, min_box_px))
