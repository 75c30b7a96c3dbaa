"""From relation scores to decisions in torch, and their docs/design.md §7 counts (``deepword.metrics``).

Batched and vectorised so the Lightning module can score whole validation batches; the predictor uses
the same functions on one image. Conventions: a decided ownership matrix is (B, N, N) bool with wheels
as rows and vehicles as columns; a decided couple matrix is symmetric.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import torch

from deepword.metrics import Counts, count_relations
from deepword.word_format import VEHICLE, WHEEL


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
                    couple: torch.Tensor, classes: torch.Tensor, evaluated: torch.Tensor) -> dict[str, torch.Tensor]:
    """The §7 counts of a batch's decisions (``deepword.metrics.count_relations``, node indices standing for box
    ids) over its evaluated wheels, ``evaluated`` (B, N): the wheels the evaluation scores, so validation
    selects the model on the metric the report gives. ``owner``/``couple`` are the symmetric 0/1 target
    matrices of ``inputs.relation_targets``."""
    wv, ww = type_masks(classes)
    batch = [t.detach().cpu().numpy() for t in (pred_owner & wv, owner.bool() & wv, pred_couple & ww,
                                                  couple.bool() & ww, classes == WHEEL, evaluated.bool())]
    total = Counts()
    for pred_o, true_o, pred_c, true_c, is_wheel, is_evaluated in zip(*batch, strict=True):
        scored = set(np.flatnonzero(is_evaluated & is_wheel).tolist())
        total = total + count_relations(
            scored, set(np.flatnonzero(is_wheel).tolist()) - scored,
            true_relations=_vehicle_wheel_pairs(true_o), true_couples=_upper_pairs(true_c),
            claimed_relations=_vehicle_wheel_pairs(pred_o), claimed_couples=_upper_pairs(pred_c))
    return {f.name: torch.tensor(getattr(total, f.name), device=classes.device) for f in fields(Counts)}


ROLE_KEYS = ("role_right", "role_known", "order_right", "order_known")


def role_counts(front: torch.Tensor, role: torch.Tensor, valid: torch.Tensor, couple: torch.Tensor) -> dict[str, torch.Tensor]:
    """Counts of the role head's answers on a batch: wheels of known role (``role`` (B, N): 1 front, 0 rear, -1
    unknown) whose front probability ``front`` (B, N) is on their side of 0.5 (``role_right`` of ``role_known``),
    and true couples (``couple`` (B, N, N), symmetric 0/1) of a front and a rear wheel whose front wheel has the
    higher probability (``order_right`` of ``order_known``): the order a predicted couple is listed in, which
    tells the vehicle's front from its back in bird's-eye view."""
    known = (role >= 0) & valid.bool()
    right = ((front > 0.5) == (role == 1)) & known
    is_front, is_rear = (role == 1) & known, (role == 0) & known
    ordered = couple.bool() & is_front.unsqueeze(2) & is_rear.unsqueeze(1)  # rows front, columns rear
    higher = front.unsqueeze(2) > front.unsqueeze(1)
    return {"role_right": right.sum(), "role_known": known.sum(), "order_right": (ordered & higher).sum(),
            "order_known": ordered.sum()}


def role_percentages(c: dict[str, float]) -> dict[str, float]:
    """``role_acc`` and ``order_acc`` (percent) of summed ``role_counts``; nothing where no role is known (a dataset
    without roles)."""
    out = {}
    if c["role_known"] > 0:
        out["role_acc"] = 100.0 * c["role_right"] / c["role_known"]
    if c["order_known"] > 0:
        out["order_acc"] = 100.0 * c["order_right"] / c["order_known"]
    return out


def _vehicle_wheel_pairs(wheel_rows: np.ndarray) -> list[tuple[int, int]]:
    """(vehicle, wheel) node pairs of a wheel-row/vehicle-column matrix."""
    wheels, vehicles = np.nonzero(wheel_rows)
    return list(zip(vehicles.tolist(), wheels.tolist(), strict=True))


def _upper_pairs(symmetric: np.ndarray) -> list[tuple[int, int]]:
    """Each pair of a symmetric matrix once."""
    a, b = np.nonzero(np.triu(symmetric, 1))
    return list(zip(a.tolist(), b.tolist(), strict=True))


def metrics_from_counts(c: dict[str, float]) -> dict[str, float]:
    """Percentages of summed ``relation_counts`` (``deepword.metrics.Counts.percentages``)."""
    return Counts(**{k: int(v) for k, v in c.items()}).percentages()
