"""Where the pair errors come from: each missed true pair and each false claim put down to one cause, so that on
detected boxes a user sees whether the detector or the relation model cost it.

Counted on exactly the pairs and claims that ``deepword.metrics.score_image`` counts (the same box matching, the
same evaluated and ignored wheels, the same ignore regions), so the causes of missed pairs add up to pair_fn and
those of false claims to pair_fp:

- a true pair of an evaluated wheel that no claim names is missed because its wheel matched no predicted box
  (``wheel_missed``), else because its vehicle did not (``vehicle_missed``), else because the two matched boxes
  were not paired (``not_paired``);
- a claim that is not a true pair, or repeats one, is false because its wheel box matches no ground-truth wheel
  (``false_wheel``), else because its vehicle box matches no ground-truth vehicle (``false_vehicle``), else
  because both boxes are real and the pair is wrong (``wrong_pair``).

``relation_oracle`` gives the other half of the answer: the predicted boxes with the ground truth's relations, what a
relation model that never errs would claim on them. Scored like any prediction it is the ceiling the boxes leave the
relation model (its false claims are none, its misses are the detector's), so the distance from a method's row to it
is what the relation model costs on those boxes, and the distance from it to 100 what the boxes cost.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from deepword.metrics import (
    _UNMATCHED as UNMATCHED,  # the scores' stand-in for a box matching no ground truth
)
from deepword.metrics import match_boxes, match_for_scoring
from deepword.word_format import Record, boxes_only

# The result row of ``relation_oracle`` beside the methods' rows (eval.<boxes>.relation_oracle.<subset>.<metric>)
RELATION_ORACLE = "relation_oracle"

# Causes of missed true pairs, then of false claims (``PairErrors`` fields, in report order), with their labels.
MISSED_CAUSES = {"wheel_missed": "wheel not detected", "vehicle_missed": "vehicle not detected",
                 "not_paired": "both detected, not paired"}
FALSE_CAUSES = {"false_wheel": "wheel box matches no wheel", "false_vehicle": "vehicle box matches no vehicle",
                "wrong_pair": "both boxes real, wrong pair"}


@dataclass
class PairErrors:
    """Pair errors by cause, summed over images: ``found`` true pairs, the missed ones by why
    (``MISSED_CAUSES``), the false claims by why (``FALSE_CAUSES``)."""

    found: int = 0
    wheel_missed: int = 0
    vehicle_missed: int = 0
    not_paired: int = 0
    false_wheel: int = 0
    false_vehicle: int = 0
    wrong_pair: int = 0

    def __add__(self, other: PairErrors) -> PairErrors:
        return PairErrors(*(getattr(self, f.name) + getattr(other, f.name) for f in fields(self)))

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def pair_errors(gt: Record, pred: Record, min_box_px: float = 0.0, match_iou: float = 0.5) -> PairErrors:
    """One image's pair errors by cause (see the module doc)."""
    evaluated, ignored, gt_id, found = match_for_scoring(gt, pred, min_box_px, match_iou)
    true_pairs = {(int(v), int(w)) for v, w, _ in gt.relations if w in evaluated}
    errors = PairErrors()
    credited: set[tuple] = set()
    for v, w, _ in pred.relations:
        vehicle, wheel = gt_id(v), gt_id(w)
        if wheel in ignored or vehicle in ignored:
            continue
        if (vehicle, wheel) in true_pairs and (vehicle, wheel) not in credited:
            credited.add((vehicle, wheel))
        elif wheel == UNMATCHED:
            errors.false_wheel += 1
        elif vehicle == UNMATCHED:
            errors.false_vehicle += 1
        else:
            errors.wrong_pair += 1
    errors.found = len(credited)
    for v, w in true_pairs - credited:
        if w not in found:
            errors.wheel_missed += 1
        elif v not in found:
            errors.vehicle_missed += 1
        else:
            errors.not_paired += 1
    return errors


def pair_errors_records(gts: list[Record], preds: dict[str, Record], min_box_px: float = 0.0,
                        match_iou: float = 0.5) -> PairErrors:
    """``pair_errors`` summed over images; an image missing from ``preds`` is its ground-truth boxes with no
    claims, as ``deepword.metrics.score_records`` scores it."""
    total = PairErrors()
    for gt in gts:
        total = total + pair_errors(gt, preds.get(gt.image) or boxes_only(gt), min_box_px, match_iou)
    return total


def relation_oracle(gt: Record, pred: Record, match_iou: float = 0.5) -> Record:
    """``pred``'s boxes with every relation and wheel couple of ``gt`` whose boxes were both found, matched as the
    scores match them (``deepword.metrics.match_boxes``); a box that matches nothing claims nothing."""
    to_pred = {g: p for p, g in match_boxes(gt, pred, match_iou).items()}
    relations = [(to_pred[v], to_pred[w], role) for v, w, role in gt.relations if v in to_pred and w in to_pred]
    couples = [(to_pred[a], to_pred[b]) for a, b in gt.wheel_pairs if a in to_pred and b in to_pred]
    return replace(pred, boxes=pred.boxes.copy(), relations=relations, wheel_pairs=couples)
