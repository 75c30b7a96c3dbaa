"""From relation scores to decisions, and the counts behind the relation metrics (docs/design.md §7), in torch.

Batched and vectorised so the Lightning module can score whole validation batches; the predictor uses
the same functions on one image. Conventions: a decided ownership matrix is (B, N, N) bool with wheels
as rows and vehicles as columns; a decided couple matrix is symmetric.
"""

from __future__ import annotations

import torch

from stages.word_format import VEHICLE, WHEEL


def type_masks(classes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N) classes -> wheel-row/vehicle-column pairs (B, N, N) and wheel-wheel pairs without self."""
    is_wheel, is_vehicle = classes == WHEEL, classes == VEHICLE
    wv = is_wheel.unsqueeze(2) & is_vehicle.unsqueeze(1)
    eye = torch.eye(classes.shape[1], dtype=torch.bool, device=classes.device)
    ww = is_wheel.unsqueeze(2) & is_wheel.unsqueeze(1) & ~eye
    return wv, ww


def inside_share(coords: torch.Tensor) -> torch.Tensor:
    """(B, N, 4) boxes -> (B, N, N): the share of row box i's area that lies inside column box j. The
    share is invariant to scaling x and y, so normalised boxes give the pixel boxes' value."""
    x1, y1, x2, y2 = coords.unbind(-1)
    iw = (torch.minimum(x2.unsqueeze(2), x2.unsqueeze(1)) - torch.maximum(x1.unsqueeze(2), x1.unsqueeze(1))).clamp_min(0)
    ih = (torch.minimum(y2.unsqueeze(2), y2.unsqueeze(1)) - torch.maximum(y1.unsqueeze(2), y1.unsqueeze(1))).clamp_min(0)
    return iw * ih / ((x2 - x1) * (y2 - y1)).clamp_min(1e-12).unsqueeze(2)


def allowed_owners(classes: torch.Tensor, cand: torch.Tensor, coords: torch.Tensor | None = None,
                   min_containment: float = 0.0) -> torch.Tensor:
    """(B, N, N) bool: the candidate wheel-vehicle pairs (wheel rows) a wheel may be given to. With
    ``min_containment`` > 0 only vehicles whose box holds at least that share of the wheel box (``coords``,
    (B, N, 4)): a vehicle's box covers its visible wheels, so a wheel sticking out of it belongs to another
    vehicle, often one too occluded to be annotated."""
    wv, _ = type_masks(classes)
    allowed = wv & cand.bool()
    if min_containment > 0:
        if coords is None:
            raise ValueError("relation decoding: min_containment needs the boxes (coords)")
        allowed = allowed & (inside_share(coords) >= min_containment)
    return allowed


def decode_owners(scores: torch.Tensor, classes: torch.Tensor, cand: torch.Tensor, threshold: float,
                  one_owner: bool, coords: torch.Tensor | None = None, min_containment: float = 0.0) -> torch.Tensor:
    """Owner decisions: every allowed wheel-vehicle pair (``allowed_owners``) above threshold, or
    (one_owner) each wheel's best-scoring allowed vehicle if that score is above threshold."""
    allowed = allowed_owners(classes, cand, coords, min_containment)
    masked = torch.where(allowed, scores, torch.full_like(scores, -2.0))  # cosines are >= -1
    above = masked > threshold
    if not one_owner:
        return above
    best = masked.argmax(dim=-1, keepdim=True)
    is_best = torch.zeros_like(above).scatter_(-1, best, True)
    return above & is_best


def decode_couples(scores: torch.Tensor, classes: torch.Tensor, cand: torch.Tensor, threshold: float) -> torch.Tensor:
    """Couple decisions: two wheels form a couple when each is the other's best-scoring wheel and the
    score is above threshold (a wheel belongs to at most one couple). Symmetric (B, N, N) bool."""
    _, ww = type_masks(classes)
    masked = torch.where(ww & cand.bool(), scores, torch.full_like(scores, -2.0))
    best = masked.argmax(dim=-1, keepdim=True)
    is_best = torch.zeros_like(ww).scatter_(-1, best, True)
    return is_best & is_best.transpose(1, 2) & (masked > threshold)


def relation_counts(pred_owner: torch.Tensor, owner: torch.Tensor, pred_couple: torch.Tensor,
                    couple: torch.Tensor, classes: torch.Tensor,
                    valid: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Counts for wheel_acc, image_acc, pair precision/recall and couple F1 over every annotated wheel in the
    graph: with ``valid`` (B, N), objects masked out of it (``small_mask_px``) are not counted, since the
    network never sees them (counted, each owned one would be a fixed error in every epoch's metric).
    ``owner``/``couple`` are the symmetric 0/1 target matrices of ``inputs.relation_targets``."""
    if valid is not None:
        classes = torch.where(valid.bool(), classes, torch.full_like(classes, -1))
    wv, ww = type_masks(classes)
    true_owner = owner.bool() & wv
    pred_owner = pred_owner & wv
    is_wheel = classes == WHEEL
    wheel_ok = (pred_owner == true_owner).all(dim=-1) & is_wheel
    wheel_wrong = is_wheel & ~wheel_ok
    upper = torch.triu(torch.ones_like(ww), diagonal=1) & ww
    true_couple, pred_couple = couple.bool() & upper, pred_couple & upper
    return {
        "wheels": is_wheel.sum(), "wheels_correct": wheel_ok.sum(),
        "images": torch.tensor(classes.shape[0], device=classes.device),
        "images_correct": (~wheel_wrong.any(dim=-1)).sum(),
        "pair_tp": (pred_owner & true_owner).sum(), "pair_fp": (pred_owner & ~true_owner).sum(),
        "pair_fn": (~pred_owner & true_owner).sum(),
        "couple_tp": (pred_couple & true_couple).sum(), "couple_fp": (pred_couple & ~true_couple).sum(),
        "couple_fn": (~pred_couple & true_couple).sum(),
    }


def _ratio(num: float, den: float, empty: float) -> float:
    return 100.0 * num / den if den > 0 else empty


def metrics_from_counts(c: dict[str, float]) -> dict[str, float]:
    """Percentages (docs/design.md §7). With nothing to find and nothing found, precision/recall/F1 are 100."""
    precision = _ratio(c["pair_tp"], c["pair_tp"] + c["pair_fp"], 100.0)
    recall = _ratio(c["pair_tp"], c["pair_tp"] + c["pair_fn"], 100.0)
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    c_den = 2 * c["couple_tp"] + c["couple_fp"] + c["couple_fn"]
    return {"wheel_acc": _ratio(c["wheels_correct"], c["wheels"], 100.0),
            "image_acc": _ratio(c["images_correct"], c["images"], 100.0),
            "pair_precision": precision, "pair_recall": recall, "pair_f1": f1,
            "couple_f1": _ratio(2 * c["couple_tp"], c_den, 100.0)}
