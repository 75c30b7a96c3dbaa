"""The wheels' front / rear roles, scored apart from the §7 metrics (docs/design.md §7), which leave them out: over
the predicted relations that name a true relation whose role is labelled. ``deepword score`` prints it; the bev stage
scores the roles ``deepword infer`` writes with it (``stages.bev.metrics.role_agreement``)."""

from __future__ import annotations

from deepword.metrics import match_boxes
from deepword.word_format import Record


def true_roles(gt: Record, pred: Record, match_iou: float = 0.5) -> dict[tuple[int, int], str]:
    """{(predicted vehicle id, predicted wheel id): the true role} of the predicted relations that name a true
    relation whose role is known (both boxes matched: ``match_boxes``): where a predicted role can be judged."""
    truth = {(v, w): r for v, w, r in gt.relations if r}
    to_gt = match_boxes(gt, pred, match_iou)
    found = {}
    for v, w, _ in pred.relations:
        role = truth.get((to_gt.get(int(v)), to_gt.get(int(w))))
        if role is not None:
            found[(v, w)] = role
    return found


def role_scores(gts: list[Record], preds: dict[str, Record], match_iou: float = 0.5) -> dict[str, float]:
    """How often the predicted relations name their wheel's role right (front / rear), over those that name a true
    relation with a known role (``true_roles``): ``role_acc`` (%; a relation without a role counts as wrong; 100
    where there is none), ``relations`` and ``without_role``, how many of them name none."""
    right = total = unnamed = 0
    for gt in gts:
        pred = preds.get(gt.image)
        if pred is None:
            continue
        judged = true_roles(gt, pred, match_iou)
        for v, w, role in pred.relations:
            if (v, w) in judged:
                total += 1
                right += role == judged[(v, w)]
                unnamed += role is None
    return {"role_acc": 100.0 * right / total if total else 100.0, "relations": float(total),
            "without_role": float(unnamed)}
