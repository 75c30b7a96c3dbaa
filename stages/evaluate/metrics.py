"""docs/design.md §7 metrics of predicted records against ground truth, in percent.

Per image, predicted boxes are first matched to ground-truth boxes of their class by IoU >= ``match_iou``,
greedily in order of decreasing score (each ground-truth box matched at most once); with predictions that
carry the ground-truth boxes this is the identity. Predicted relations and couples are then translated to
ground-truth box ids; one whose box is unmatched (or names a box that does not exist) cannot be right.

Definitions (micro-averaged over the images of a subset):

- evaluated wheels: ground-truth wheels whose shorter box side is >= ``min_box_px``; only they, their
  relations and their couples are scored. A prediction touching a ground-truth wheel that is *not*
  evaluated is ignored (neither right nor wrong), so every method is judged on the same objects.
- wheel_acc: share of evaluated wheels whose predicted owner equals the true owner, "no owner" being a
  value. A wheel no detection matched is wrong; a wheel given two different owners is wrong.
- pair_precision / pair_recall / pair_f1 over (vehicle, wheel) relations. Every predicted relation entry
  counts: a duplicate of a correct one is a false positive.
- couple_f1 over wheel pairs, unordered (the front/rear order is a role, scored by neither metric).
- image_acc: share of images in which every evaluated wheel is right; an image without evaluated
  wheels (e.g. no vehicles, no wheels) is vacuously right.
- Empty denominators never give NaN: a ratio with nothing to count (0/0) is 100 (nothing was
  missed / nothing wrong was claimed); F1 with precision + recall = 0 is 0.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from stages.geometry import pairwise_iou
from stages.word_format import WHEEL, Record

METRICS = ("wheel_acc", "pair_precision", "pair_recall", "pair_f1", "couple_f1", "image_acc")
_UNMATCHED = "unmatched"  # stands for a predicted box that matched no ground truth: equal to no true id


@dataclass
class Counts:
    """Counts summed over images; ``percentages()`` turns them into the §7 metrics."""

    images: int = 0
    images_correct: int = 0
    wheels: int = 0
    wheels_correct: int = 0
    pair_tp: int = 0
    pair_fp: int = 0
    pair_fn: int = 0
    couple_tp: int = 0
    couple_fp: int = 0
    couple_fn: int = 0

    def __add__(self, other: Counts) -> Counts:
        return Counts(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    def percentages(self) -> dict[str, float]:
        pp, pr = _pct(self.pair_tp, self.pair_tp + self.pair_fp), _pct(self.pair_tp, self.pair_tp + self.pair_fn)
        cp = _pct(self.couple_tp, self.couple_tp + self.couple_fp)
        cr = _pct(self.couple_tp, self.couple_tp + self.couple_fn)
        return {"wheel_acc": _pct(self.wheels_correct, self.wheels), "pair_precision": pp, "pair_recall": pr,
                "pair_f1": _f1(pp, pr), "couple_f1": _f1(cp, cr),
                "image_acc": _pct(self.images_correct, self.images)}


def _pct(num: int, den: int) -> float:
    return 100.0 * num / den if den else 100.0


def _f1(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if p + r > 0 else 0.0


def evaluated_wheel_ids(gt: Record, min_box_px: float) -> set[int]:
    """Box ids of the ground-truth wheels every method is scored on."""
    xyxy, ids = gt.xyxy, gt.box_ids
    short = np.minimum(xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1])
    return {int(i) for i, c, s in zip(ids, gt.class_ids, short, strict=True) if c == WHEEL and s >= min_box_px}


def match_boxes(gt: Record, pred: Record, match_iou: float = 0.5) -> dict[int, int]:
    """predicted box_id -> ground-truth box_id, per class by IoU >= match_iou, greedily by score."""
    out: dict[int, int] = {}
    for cls in np.unique(pred.class_ids):
        p_idx = np.flatnonzero(pred.class_ids == cls)
        g_idx = np.flatnonzero(gt.class_ids == cls)
        if not len(g_idx):
            continue
        iou = pairwise_iou(pred.xyxy[p_idx], gt.xyxy[g_idx])
        taken = np.zeros(len(g_idx), dtype=bool)
        for row in np.argsort(-pred.scores[p_idx], kind="stable"):
            cand = np.where(taken, -1.0, iou[row])
            best = int(np.argmax(cand))
            if cand[best] >= match_iou:
                taken[best] = True
                out[int(pred.box_ids[p_idx[row]])] = int(gt.box_ids[g_idx[best]])
    return out


def score_image(gt: Record, pred: Record, min_box_px: float = 0.0, match_iou: float = 0.5) -> Counts:
    """§7 counts of one image's prediction against its ground truth."""
    evaluated = evaluated_wheel_ids(gt, min_box_px)
    all_gt_wheels = {int(b) for b, c in zip(gt.box_ids, gt.class_ids, strict=True) if c == WHEEL}
    ignored = all_gt_wheels - evaluated
    to_gt = match_boxes(gt, pred, match_iou)

    def gt_id(pred_id: int) -> int | str:
        return to_gt.get(int(pred_id), _UNMATCHED)

    # pairs (vehicle, wheel)
    true_pairs = {(v, w) for v, w, _ in gt.relations if w in evaluated}
    claimed = [(gt_id(v), gt_id(w)) for v, w, _ in pred.relations]
    claimed = [p for p in claimed if p[1] not in ignored]
    pair_tp = len(true_pairs & set(claimed))

    # couples, unordered
    true_couples = {frozenset(p) for p in gt.wheel_pairs if set(p) <= evaluated}
    claimed_c = [frozenset((gt_id(a), gt_id(b))) for a, b in pred.wheel_pairs]
    claimed_c = [c for c in claimed_c if not (c & ignored)]
    couple_tp = len(true_couples & set(claimed_c))

    # owners of evaluated wheels
    true_owner = gt.owner_of()
    pred_owners: dict[int, set[int]] = {}
    for v, w, _ in pred.relations:
        pred_owners.setdefault(int(w), set()).add(gt_id(v))
    gt_to_pred = {g: p for p, g in to_gt.items()}
    correct = 0
    for w in evaluated:
        if w not in gt_to_pred:
            continue  # missed by the detector: cannot be right
        owners = pred_owners.get(gt_to_pred[w], set())
        if len(owners) > 1:
            continue
        predicted = next(iter(owners)) if owners else None
        correct += predicted == true_owner.get(w)
    return Counts(images=1, images_correct=int(correct == len(evaluated)), wheels=len(evaluated),
                  wheels_correct=correct, pair_tp=pair_tp, pair_fp=len(claimed) - pair_tp,
                  pair_fn=len(true_pairs) - pair_tp, couple_tp=couple_tp, couple_fp=len(claimed_c) - couple_tp,
                  couple_fn=len(true_couples) - couple_tp)


def score_records(gts: list[Record], preds: dict[str, Record], min_box_px: float = 0.0,
                  match_iou: float = 0.5) -> Counts:
    """Sum of per-image counts. An image missing from ``preds`` counts as predicted with no relations and
    no couples (on its ground-truth boxes, so a wheel truly without owner is right there)."""
    total = Counts()
    for gt in gts:
        pred = preds.get(gt.image)
        if pred is None:
            pred = Record(image=gt.image, frame_id=gt.frame_id, camera=gt.camera, width=gt.width,
                          height=gt.height, boxes=gt.boxes.copy(), relations=[], wheel_pairs=[])
        total = total + score_image(gt, pred, min_box_px, match_iou)
    return total
