"""Relation decisions from ONNX scores, in numpy: the same rules as ``stages.relation.decode`` (which works
on torch tensors for training), for runtimes without torch. ``tests/stages/export`` checks that both give
identical decisions on random scores, so the two cannot drift apart.

Conventions as there: (B, N, N) scores, wheels as rows and vehicles as columns for ownership; a decided
couple matrix is symmetric.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from deepword.geometry import containment
from deepword.word_format import VEHICLE, WHEEL, Record

_BELOW_ANY_COSINE = -2.0  # masked entries: cosines are >= -1


def type_masks(classes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, N) classes -> wheel-row/vehicle-column pairs (B, N, N) and wheel-wheel pairs without self."""
    is_wheel, is_vehicle = classes == WHEEL, classes == VEHICLE
    wv = is_wheel[:, :, None] & is_vehicle[:, None, :]
    ww = is_wheel[:, :, None] & is_wheel[:, None, :] & ~np.eye(classes.shape[1], dtype=bool)
    return wv, ww


def _is_row_best(masked: np.ndarray) -> np.ndarray:
    """One True per row, at the row's argmax (first one on ties, as torch.argmax on CPU)."""
    best = masked.argmax(axis=-1)[..., None]
    return np.arange(masked.shape[-1]) == best


def decode_owners(scores: np.ndarray, classes: np.ndarray, cand: np.ndarray, threshold: float,
                  one_owner: bool, coords: np.ndarray | None = None, min_containment: float = 0.0) -> np.ndarray:
    """Every candidate wheel-vehicle pair above threshold, or (one_owner) each wheel's best vehicle if
    its score is above threshold; with ``min_containment`` > 0 only vehicles whose box holds that share
    of the wheel box (``coords``)."""
    wv, _ = type_masks(classes)
    allowed = wv & cand.astype(bool)
    if min_containment > 0:
        if coords is None:
            raise ValueError("decode_owners: min_containment needs the boxes (coords)")
        allowed &= np.stack([containment(boxes, boxes) for boxes in coords]) >= min_containment
    masked = np.where(allowed, scores, _BELOW_ANY_COSINE)
    above = masked > threshold
    return above & _is_row_best(masked) if one_owner else above


def decode_couples(scores: np.ndarray, classes: np.ndarray, cand: np.ndarray, threshold: float) -> np.ndarray:
    """Two wheels form a couple when each is the other's best-scoring wheel and the score is above threshold."""
    _, ww = type_masks(classes)
    masked = np.where(ww & cand.astype(bool), scores, _BELOW_ANY_COSINE)
    best = _is_row_best(masked)
    return best & best.transpose(0, 2, 1) & (masked > threshold)


def prediction_record(rec: Record, pred_owner: np.ndarray, pred_couple: np.ndarray, front: np.ndarray,
                      has_roles: bool) -> Record:
    """The record with its boxes unchanged and the decided relations and couples (wheel rows, vehicle
    columns in ``pred_owner``; symmetric ``pred_couple``; ``front`` probabilities)."""
    ids = rec.box_ids
    n = len(ids)
    relations = []
    for w, v in zip(*np.nonzero(pred_owner[:n, :n]), strict=True):
        role = ("front" if front[w] > 0.5 else "rear") if has_roles else None
        relations.append((int(ids[v]), int(ids[w]), role))
    pairs = []
    centre_x = (rec.xyxy[:, 0] + rec.xyxy[:, 2]) / 2 if n else np.zeros(0)
    for a, b in zip(*np.nonzero(np.triu(pred_couple[:n, :n], 1)), strict=True):
        rear_first = front[a] <= front[b] if has_roles else centre_x[a] <= centre_x[b]
        pairs.append((int(ids[a]), int(ids[b])) if rear_first else (int(ids[b]), int(ids[a])))
    return dataclasses.replace(rec, relations=sorted(relations), wheel_pairs=sorted(pairs))

