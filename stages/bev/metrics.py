"""Bird's-eye-view footprint metrics, nuScenes-style where they fit.

Per frame, estimated footprints are matched to true vehicles greedily by BEV centre distance (closest pairs
first) up to ``match_m`` (2 m). Per matched vehicle: centre error (m, nuScenes' ATE), heading error (deg,
modulo 180: no method predicts which end is the front), corner error (m: mean distance of the four
corners, the better of the two directions) and the BEV IoU of the two footprints (shapely). Recall is the
share of true vehicles matched. Aggregates are medians over matched vehicles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from shapely.geometry import Polygon

from stages.format_3d import Box3D

METRICS = ("center_err_m", "heading_err_deg", "corner_err_m", "bev_iou", "recall")


@dataclass
class TrueVehicle:
    """A vehicle of a frame (deduplicated over its cameras) and the populations it belongs to."""

    box: Box3D
    paired: bool = False   # two same-side wheels annotated in at least one of the frame's images
    hard: bool = False     # annotated in an image of the hard test subset

    @property
    def range_m(self) -> float:
        """Distance from the vehicle frame's origin (on the ground under the ego's rear axle)."""
        return math.hypot(self.box.x, self.box.y)


@dataclass
class Match:
    truth: TrueVehicle
    estimate: Box3D | None    # None: missed

    def errors(self) -> dict[str, float]:
        if self.estimate is None:
            return {}
        t, e = self.truth.box, self.estimate
        heading = abs(math.degrees(math.remainder(e.yaw - t.yaw, math.pi)))
        tc, ec = t.corners(), e.corners()
        corner = min(float(np.linalg.norm(tc - ec, axis=1).mean()),
                     float(np.linalg.norm(tc - np.roll(ec, 2, axis=0), axis=1).mean()))
        return {"center_err_m": math.hypot(e.x - t.x, e.y - t.y), "heading_err_deg": heading,
                "corner_err_m": corner, "bev_iou": bev_iou(t, e)}


def bev_iou(a: Box3D, b: Box3D) -> float:
    pa, pb = Polygon(a.corners()), Polygon(b.corners())
    union = pa.union(pb).area
    return float(pa.intersection(pb).area / union) if union > 0 else 0.0


def match_frame(truth: list[TrueVehicle], estimates: list[Box3D], match_m: float) -> list[Match]:
    """Greedy one-to-one matching by centre distance <= match_m; one Match per true vehicle."""
    pairs = sorted((math.hypot(t.box.x - e.x, t.box.y - e.y), i, j)
                   for i, t in enumerate(truth) for j, e in enumerate(estimates))
    taken_t, taken_e, found = set(), set(), {}
    for d, i, j in pairs:
        if d > match_m:
            break
        if i in taken_t or j in taken_e:
            continue
        taken_t.add(i)
        taken_e.add(j)
        found[i] = estimates[j]
    return [Match(t, found.get(i)) for i, t in enumerate(truth)]


def summarise(matches: list[Match]) -> dict[str, float]:
    """Medians of the matched vehicles' errors and the recall; NaN medians when nothing matched."""
    errs = [m.errors() for m in matches if m.estimate is not None]
    out = {k: float(np.median([e[k] for e in errs])) if errs else float("nan") for k in METRICS[:-1]}
    out["recall"] = 100.0 * len(errs) / len(matches) if matches else float("nan")
    out["vehicles"] = float(len(matches))
    return out
