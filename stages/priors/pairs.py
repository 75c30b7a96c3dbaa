"""Candidate pairs of a record and their Eq. 2 distance ratios, labelled true pair or not.

Wheel-vehicle candidates are every (vehicle A, wheel B) combination. Wheel-wheel candidates are every
ordered (A, B) of two different wheels; a true pair is an annotated couple (A = rear, B = front). The
reversed order of a true couple (front, rear) is the same couple, not a non-pair, so it is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deepword.geometry import pairwise_distance_ratio
from deepword.word_format import VEHICLE, WHEEL, Record

PAIR_TYPES = ("wheel_vehicle", "wheel_wheel")


@dataclass
class LabelledRatios:
    """Distance ratios of one pair type, split into true pairs and non-pairs."""

    pairs: np.ndarray
    non_pairs: np.ndarray


def record_ratios(rec: Record) -> dict[str, LabelledRatios]:
    """Both pair types' ratios for one record."""
    ids = rec.box_ids
    vehicles = np.flatnonzero(rec.class_ids == VEHICLE)
    wheels = np.flatnonzero(rec.class_ids == WHEEL)
    owner = rec.owner_of()

    wv = pairwise_distance_ratio(rec.xyxy[vehicles], rec.xyxy[wheels], rec.width, rec.height)
    wv_true = np.array([[owner.get(int(ids[w])) == int(ids[v]) for w in wheels] for v in vehicles], dtype=bool)
    wv_true = wv_true.reshape(wv.shape)

    ww = pairwise_distance_ratio(rec.xyxy[wheels], rec.xyxy[wheels], rec.width, rec.height)
    couples = {(a, b) for a, b in rec.wheel_pairs}
    wheel_ids = [int(ids[w]) for w in wheels]
    ww_true = np.array([[(a, b) in couples for b in wheel_ids] for a in wheel_ids], dtype=bool).reshape(ww.shape)
    ww_keep = ~np.eye(len(wheels), dtype=bool) & ~ww_true.T  # drop self pairs and reversed couples
    return {
        "wheel_vehicle": LabelledRatios(wv[wv_true], wv[~wv_true]),
        "wheel_wheel": LabelledRatios(ww[ww_true], ww[ww_keep & ~ww_true]),
    }


def collect_ratios(records: list[Record]) -> dict[str, LabelledRatios]:
    """Concatenate every record's ratios per pair type."""
    parts = [record_ratios(r) for r in records]
    out = {}
    for kind in PAIR_TYPES:
        out[kind] = LabelledRatios(
            np.concatenate([p[kind].pairs for p in parts]) if parts else np.zeros(0),
            np.concatenate([p[kind].non_pairs for p in parts]) if parts else np.zeros(0),
        )
    return out
