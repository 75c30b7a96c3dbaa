"""Training records that look like a detector's output: what the relation network sees end to end.

Trained on annotated boxes only, the network has never seen a box that stops short of the wheels, a wheel
without its vehicle, or a vehicle box on a shop front; at test time a detector gives it all three. So the
relation stage can add, per training image, copies whose boxes are perturbed the way detections differ
from labels (the SGDet setting of scene-graph work, simulated rather than taken from one detector so that
the relation stage keeps depending on the data alone):

- jitter: each side of each box moves by a Gaussian share (std ``jitter``) of the box's width or height;
- drop: each box is missed with probability ``drop``; a relation or couple naming a missed box goes with it;
- false positives: about ``false_positives`` x (number of boxes) extra boxes of either class, each a
  labelled box of that class moved by one to two of its sizes, or resized about its own centre so that
  it matches no label (IoU < 0.5). A false positive owns nothing and belongs to nothing.

Relations and couples are only ever removed, never invented, so every target stays true of the boxes
that remain.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from deepword.geometry import pairwise_iou
from deepword.word_format import Record

MATCH_IOU = 0.5       # a false positive must not pass for a label at the evaluation's matching IoU
MIN_SIDE_PX = 2.0     # a perturbed box keeps at least this size


@dataclass(frozen=True)
class DetectionNoise:
    copies: int = 0               # perturbed copies per training image (0: annotated boxes only)
    jitter: float = 0.08          # std of each side's shift, as a share of the box's width / height
    drop: float = 0.08            # probability that a box is missed
    false_positives: float = 0.1  # expected extra boxes per labelled box

    @classmethod
    def from_cfg(cls, cfg) -> DetectionNoise:
        if cfg is None:
            return cls()
        return cls(copies=int(cfg.copies), jitter=float(cfg.jitter), drop=float(cfg.drop),
                   false_positives=float(cfg.false_positives))


def _clip(xyxy: np.ndarray, width: int, height: int) -> np.ndarray:
    out = xyxy.copy()
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, width)
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, height)
    return out


def _false_positive(rng: np.random.Generator, box: np.ndarray, width: int, height: int) -> np.ndarray:
    """A box derived from a labelled one: moved by 1-2 of its sizes, or resized 0.4x / 2x about its centre."""
    x1, y1, x2, y2 = box
    w, h = x2 - x1, y2 - y1
    if rng.random() < 0.5:
        dx, dy = rng.uniform(1.0, 2.0, 2) * rng.choice([-1.0, 1.0], 2) * np.array([w, h])
        dy *= rng.random() < 0.5  # mostly sideways, as neighbouring structure is
        new = np.array([x1 + dx, y1 + dy, x2 + dx, y2 + dy])
    else:
        s = rng.choice([0.4, 2.0]) * rng.uniform(0.9, 1.1)
        cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
        new = np.array([cx - s * w / 2, cy - s * h / 2, cx + s * w / 2, cy + s * h / 2])
    return _clip(new[None], width, height)[0]


def simulate_detections(record: Record, noise: DetectionNoise, rng: np.random.Generator,
                        max_objects: int | None = None) -> Record:
    """``record`` as a detector might have seen it (see the module doc). Kept boxes keep their ids; false
    positives get new ids; relations and couples only lose entries whose boxes were missed."""
    boxes = record.boxes.copy()
    xyxy = boxes[:, :4]
    size = np.stack([xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1]], axis=1)
    shift = rng.normal(0.0, noise.jitter, (len(boxes), 4)) * np.tile(size, 2)
    moved = _clip(xyxy + shift, record.width, record.height)
    too_small = (moved[:, 2] - moved[:, 0] < MIN_SIDE_PX) | (moved[:, 3] - moved[:, 1] < MIN_SIDE_PX)
    boxes[:, :4] = np.where(too_small[:, None], xyxy, moved)
    kept = boxes[rng.random(len(boxes)) >= noise.drop]
    kept_ids = {int(b) for b in kept[:, 6]}

    extra = []
    n_fp = rng.poisson(noise.false_positives * len(record.boxes)) if len(record.boxes) else 0
    if max_objects is not None:
        n_fp = min(n_fp, max_objects - len(kept))
    next_id = int(record.boxes[:, 6].max()) + 1 if len(record.boxes) else 0
    for _ in range(max(0, n_fp)):
        source = record.boxes[rng.integers(len(record.boxes))]
        cls = int(source[5])
        candidate = _false_positive(rng, source[:4], record.width, record.height)
        if min(candidate[2] - candidate[0], candidate[3] - candidate[1]) < MIN_SIDE_PX:
            continue
        same_class = record.boxes[record.boxes[:, 5] == cls, :4]
        if len(same_class) and pairwise_iou(candidate[None], same_class).max() >= MATCH_IOU:
            continue
        extra.append([*candidate, 1.0, cls, next_id])
        next_id += 1
    all_boxes = np.concatenate([kept, np.asarray(extra, dtype=np.float64).reshape(-1, 7)])
    relations = [(v, w, r) for v, w, r in record.relations if v in kept_ids and w in kept_ids]
    couples = [(a, b) for a, b in record.wheel_pairs if a in kept_ids and b in kept_ids]
    return replace(record, boxes=all_boxes, relations=relations, wheel_pairs=couples)


def with_simulated_detections(records: list[Record], noise: DetectionNoise, seed: int,
                              max_objects: int | None = None) -> list[Record]:
    """``records`` followed by ``noise.copies`` perturbed copies of each (seeded: the same list every run)."""
    rng = np.random.default_rng(seed)
    copies = [simulate_detections(r, noise, rng, max_objects) for _ in range(noise.copies) for r in records]
    return list(records) + copies
