"""The docs/design.md §7 metrics, in percent: the one implementation, used by relation validation (model
selection), baseline fitting and evaluation.

Per image, predicted boxes are first matched to ground-truth boxes of their class by IoU >= ``match_iou``,
greedily in order of decreasing score (each ground-truth box matched at most once); with predictions that
carry the ground-truth boxes this is the identity. Predicted relations and couples are then translated to
ground-truth box ids; one whose box is unmatched (or names a box that does not exist) cannot be right.

Definitions (micro-averaged over the images of a subset):

- evaluated wheels: ground-truth wheels whose shorter box side is >= ``min_box_px``; only they, their
  relations and their couples are scored. A prediction touching a ground-truth wheel that is *not*
  evaluated is ignored (neither right nor wrong), so every method is judged on the same objects.
- ignore regions (``Record.ignore``: objects visible but not annotated, e.g. too hidden to label): a predicted
  box matching no ground truth that lies mostly inside one of its class (intersection >= ``match_iou`` of the
  box's area, COCO's crowd rule) is ignored too, and so is every relation or couple that names it.
- wheel_acc: share of evaluated wheels whose predicted owner equals the true owner, "no owner" being a
  value. A wheel no detection matched is wrong; a wheel given two different owners is wrong.
- pair_precision / pair_recall / pair_f1 over (vehicle, wheel) relations. Every predicted relation entry
  counts: a duplicate of a correct one is a false positive.
- couple_f1 over wheel pairs, unordered (the front/rear order is a role, scored by neither metric).
- image_acc: share of images in which every evaluated wheel is right; an image without evaluated
  wheels (e.g. no vehicles, no wheels) is vacuously right.
- Every caller counts through ``count_relations`` and turns counts into percentages with
  ``Counts.percentages``: the evaluate stage on records (``score_image``), the baselines on their owner
  indices, relation validation on its decoded matrices.
- Empty denominators never give NaN: a ratio with nothing to count (0/0) is 100 (nothing was
  missed / nothing wrong was claimed); F1 with precision + recall = 0 is 0.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Sequence
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from deepword.geometry import containment, pairwise_iou
from deepword.word_format import WHEEL, Record

METRICS = ("wheel_acc", "pair_precision", "pair_recall", "pair_f1", "couple_f1", "image_acc")
_UNMATCHED = "unmatched"  # stands for a predicted box that matched no ground truth: equal to no true id
_IGNORED = "ignored"  # stands for an unmatched predicted box inside an ignore region: counted neither way


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


def evaluated_mask(xyxy: np.ndarray, class_ids: np.ndarray, min_box_px: float) -> np.ndarray:
    """Which boxes are evaluated wheels: wheels whose shorter side is at least ``min_box_px`` pixels."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    short = np.minimum(xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1])
    return (np.asarray(class_ids) == WHEEL) & (short >= min_box_px)


def evaluated_wheel_ids(gt: Record, min_box_px: float) -> set[int]:
    """Box ids of the ground-truth wheels every method is scored on."""
    return {int(i) for i in gt.box_ids[evaluated_mask(gt.xyxy, gt.class_ids, min_box_px)]}


def count_relations(evaluated: set[int], ignored: set[int], true_relations: Iterable[tuple[int, int]],
                    true_couples: Iterable[tuple[int, int]], claimed_relations: Sequence[tuple[Hashable, Hashable]],
                    claimed_couples: Sequence[tuple[Hashable, Hashable]], found: set[int] | None = None) -> Counts:
    """§7 counts of one image, every id a ground-truth box id (or a stand-in for an unmatched prediction).

    ``evaluated``: the scored wheels; ``ignored``: the other ground-truth wheels, whose claims count neither
    way; ``true_*``: (vehicle, wheel) relations and wheel couples of the ground truth; ``claimed_*``: the
    prediction's, one entry per claim (a repeated claim is a false positive); ``found``: the ground-truth
    wheels a predicted box stands for (None: all; a wheel not found cannot be right)."""
    true_pairs = {(v, w) for v, w in true_relations if w in evaluated}
    claimed = [(v, w) for v, w in claimed_relations if w not in ignored and v not in ignored]
    pair_tp = len(true_pairs & set(claimed))

    true_c = {frozenset(c) for c in true_couples if set(c) <= evaluated}
    claimed_c = [frozenset(c) for c in claimed_couples]
    claimed_c = [c for c in claimed_c if not (c & ignored)]
    couple_tp = len(true_c & set(claimed_c))

    true_owner = {w: v for v, w in true_relations}
    pred_owners: dict[Hashable, set[Hashable]] = {}
    for v, w in claimed_relations:
        if v not in ignored:  # a claim by a box in an ignore region counts neither way
            pred_owners.setdefault(w, set()).add(v)
    correct = 0
    for w in evaluated:
        if found is not None and w not in found:
            continue
        owners = pred_owners.get(w, set())
        if len(owners) > 1:
            continue
        correct += (next(iter(owners)) if owners else None) == true_owner.get(w)
    return Counts(images=1, images_correct=int(correct == len(evaluated)), wheels=len(evaluated),
                  wheels_correct=correct, pair_tp=pair_tp, pair_fp=len(claimed) - pair_tp,
                  pair_fn=len(true_pairs) - pair_tp, couple_tp=couple_tp, couple_fp=len(claimed_c) - couple_tp,
                  couple_fn=len(true_c) - couple_tp)


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


def in_ignore_regions(gt: Record, pred: Record, to_gt: dict[int, int], match_iou: float = 0.5) -> set[int]:
    """Ids of the predicted boxes that matched nothing (``to_gt`` of ``match_boxes``) and lie mostly inside an
    ignore region of their class: at least ``match_iou`` of the box's area, COCO's rule for its crowd regions."""
    if not len(gt.ignore) or not len(pred.boxes):
        return set()
    inside = containment(pred.xyxy, gt.ignore[:, :4]) >= match_iou
    same_class = pred.class_ids[:, None] == gt.ignore[None, :, 4].astype(int)
    return {int(b) for b, hit in zip(pred.box_ids, (inside & same_class).any(axis=1), strict=True)
            if hit and int(b) not in to_gt}


class Matching(NamedTuple):
    """How every score sees one image: the evaluated wheel ids; the ignored ids (the wheels too small to evaluate,
    and ``_IGNORED``, the stand-in of a predicted box in an ignore region); ``gt_id``: predicted box id -> the
    ground-truth id it matched, else ``_IGNORED`` or ``_UNMATCHED``; ``found``: the ground-truth ids matched."""
    evaluated: set[int]
    ignored: set[Hashable]
    gt_id: Callable[[int], Hashable]
    found: set[int]


def match_for_scoring(gt: Record, pred: Record, min_box_px: float = 0.0, match_iou: float = 0.5) -> Matching:
    evaluated = evaluated_wheel_ids(gt, min_box_px)
    ignored: set[Hashable] = {int(b) for b, c in zip(gt.box_ids, gt.class_ids, strict=True) if c == WHEEL} - evaluated
    to_gt = match_boxes(gt, pred, match_iou)
    hidden = in_ignore_regions(gt, pred, to_gt, match_iou)
    if hidden:
        ignored.add(_IGNORED)

    def gt_id(pred_id: int) -> Hashable:
        pred_id = int(pred_id)
        return to_gt.get(pred_id, _IGNORED if pred_id in hidden else _UNMATCHED)

    return Matching(evaluated, ignored, gt_id, set(to_gt.values()))


def score_image(gt: Record, pred: Record, min_box_px: float = 0.0, match_iou: float = 0.5) -> Counts:
    """§7 counts of one image's prediction against its ground truth."""
    m = match_for_scoring(gt, pred, min_box_px, match_iou)
    return count_relations(m.evaluated, m.ignored, [(v, w) for v, w, _ in gt.relations], gt.wheel_pairs,
                           [(m.gt_id(v), m.gt_id(w)) for v, w, _ in pred.relations],
                           [(m.gt_id(a), m.gt_id(b)) for a, b in pred.wheel_pairs], found=m.found)


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
