"""Bird's-eye-view footprint metrics.

``detection_scores`` scores the fused footprints of every frame the nuScenes way (docs/bev.md, "Scoring"): AP
with centre-distance matching at 0.5 / 1 / 2 / 4 m over estimates ranked by confidence, and the true-positive
errors ATE, ASE, AOE (over 360 deg and modulo 180 deg) at 2 m, per subset of true vehicles.

The paired medians (``match_frame``, ``summarise``, kept so that their history reads on): per frame, estimated footprints are matched to true vehicles greedily by BEV centre distance (closest pairs
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

from deepword.format_3d import Box3D

METRICS = ("center_err_m", "heading_err_deg", "corner_err_m", "bev_iou", "recall")


@dataclass
class TrueVehicle:
    """A vehicle of a frame (deduplicated over its cameras) and the populations it belongs to."""

    box: Box3D
    paired: bool = False   # two same-side wheels annotated in at least one of the frame's images
    hard: bool = False     # annotated in an image of the hard test subset
    wheels: int = 0        # most of its wheels annotated in one of the frame's images, capped at 2 (its population)

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


# --- nuScenes-style detection scoring on the frame ------------------------------------------------------------
#
# nuScenes' detection AP (nuscenes-devkit, eval/detection/algo.py): estimates of all frames ranked by confidence,
# each matched in that order to the nearest not yet taken true vehicle of its frame whose BEV centre lies closer
# than the threshold; the precision-recall curve sampled at 101 recall levels (precision 0 beyond the highest
# recall reached); AP = the mean over the recall levels above MIN_RECALL of max(precision - MIN_PRECISION, 0),
# divided by 1 - MIN_PRECISION (so a perfect curve gives 1). TP errors (ATE, ASE, AOE) at TP_THRESHOLD: the
# running mean of the matches' errors in confidence order, read at each recall level, averaged over the recall
# levels above MIN_RECALL up to the highest recall reached.

DIST_THRESHOLDS = (0.5, 1.0, 2.0, 4.0)
TP_THRESHOLD = 2.0
MIN_RECALL = 0.1
MIN_PRECISION = 0.1
RECALL_LEVELS = 101
# ``recall_at_p95``: the most of the subset's vehicles found at a confidence threshold whose estimates are at least
# this precise (at TP_THRESHOLD): one point of the precision-recall curve, where a user would put the threshold
OPERATING_PRECISION = 0.95


def ap_key(threshold: float) -> str:
    """``ap_0p5m``, ``ap_1m``, ``ap_2m``, ``ap_4m``: AP (%) at one centre-distance threshold."""
    return "ap_" + f"{threshold:g}".replace(".", "p") + "m"


DETECTION_METRICS = ("ap", *(ap_key(t) for t in DIST_THRESHOLDS), "ate_m", "ase", "aoe_rad", "aoe_deg",
                     "aoe180_deg", "iou", "center_err_median_m", "recall", "precision", "recall_at_p95", "vehicles",
                     "estimates")


@dataclass(frozen=True)
class Scored:
    """A fused footprint as the detection scoring sees it."""

    box: Box3D
    confidence: float        # ranks the estimates (docs/bev.md: from its evidence and its boxes' scores)
    wheels: int = 0          # wheels its evidence rests on (0, 1, 2 = two or more; reported, not a subset rule)

    @property
    def range_m(self) -> float:
        return math.hypot(self.box.x, self.box.y)


def yaw_error(a: float, b: float, period: float = 2 * math.pi) -> float:
    """Smallest angle (rad) between two headings, modulo ``period`` (2 pi: front and back told apart; pi: axes)."""
    return abs(math.remainder(a - b, period))


def scale_error(truth: Box3D, est: Box3D) -> float:
    """nuScenes' ASE: 1 - the 3D IoU of the two boxes with centre and heading aligned (sizes only)."""
    inter = min(truth.length, est.length) * min(truth.width, est.width) * min(truth.height, est.height)
    union = truth.length * truth.width * truth.height + est.length * est.width * est.height - inter
    return 1.0 - inter / union if union > 0 else 1.0


def match_errors(truth: Box3D, est: Box3D) -> dict[str, float]:
    return {"ate_m": math.hypot(est.x - truth.x, est.y - truth.y), "ase": scale_error(truth, est),
            "aoe_rad": yaw_error(est.yaw, truth.yaw), "aoe180_rad": yaw_error(est.yaw, truth.yaw, math.pi),
            "iou": bev_iou(truth, est)}


def match_by_confidence(truth: list[Box3D], estimates: list[Scored], threshold: float) -> list[int | None]:
    """nuScenes' matching in one frame: estimates by falling confidence, each to the nearest untaken true vehicle
    closer than ``threshold`` (strictly). Returns, per estimate in the given order, the true index or None."""
    taken, out = set(), [None] * len(estimates)
    for j in sorted(range(len(estimates)), key=lambda j: -estimates[j].confidence):
        e = estimates[j]
        best, best_d = None, math.inf
        for i, t in enumerate(truth):
            if i not in taken:
                d = math.hypot(t.x - e.box.x, t.y - e.box.y)
                if d < best_d:
                    best, best_d = i, d
        if best is not None and best_d < threshold:
            taken.add(best)
            out[j] = best
    return out


def average_precision(precision: np.ndarray) -> float:
    """nuScenes' calc_ap on a precision curve sampled at RECALL_LEVELS recall levels (0..1), as a fraction."""
    prec = np.array(precision, dtype=np.float64)[round(100 * MIN_RECALL) + 1:] - MIN_PRECISION
    prec[prec < 0] = 0
    return float(np.mean(prec)) / (1.0 - MIN_PRECISION)


def pr_curve(tp: np.ndarray, confidence: np.ndarray, n_true: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(recall levels, precision, confidence) at RECALL_LEVELS recall levels from the ranked true/false flags."""
    tp_c = np.cumsum(tp).astype(np.float64)
    fp_c = np.cumsum(1 - tp).astype(np.float64)
    levels = np.linspace(0, 1, RECALL_LEVELS)
    if not len(tp) or tp_c[-1] == 0:
        return levels, np.zeros(RECALL_LEVELS), np.zeros(RECALL_LEVELS)
    recall = tp_c / n_true
    precision = tp_c / (tp_c + fp_c)
    return levels, np.interp(levels, recall, precision, right=0), np.interp(levels, recall, confidence, right=0)


def recall_at_precision(tp: np.ndarray, confidence: np.ndarray, n_true: int, precision: float) -> float:
    """The highest recall (0-1) over the confidence thresholds (``tp``, ``confidence``: the ranked estimates, confidence
    falling) at which the estimates kept are at least ``precision`` precise; a threshold keeps every estimate of a
    tied confidence or none. 0 when none is."""
    if not len(tp) or n_true == 0:
        return 0.0
    tp_c = np.cumsum(tp).astype(np.float64)
    kept = np.arange(1, len(tp) + 1, dtype=np.float64)
    at_threshold = np.append(confidence[1:] != confidence[:-1], True)   # the last estimate of each confidence
    ok = at_threshold & (tp_c >= precision * kept - 1e-12)
    return float(tp_c[ok].max() / n_true) if ok.any() else 0.0


def tp_error(errors: np.ndarray, match_conf: np.ndarray, level_conf: np.ndarray) -> float:
    """nuScenes' calc_tp: the running mean of the matches' errors (confidence order) read at each recall level's
    confidence, averaged over the recall levels above MIN_RECALL up to the highest one reached; NaN without matches.
    Matches of equal confidence are one step of the curve: the running mean read at their confidence includes all of
    them (interpolating between tied points would read one arbitrary match's share of it: on ground-truth boxes,
    where every estimate of an evidence level has the same confidence, the first few matches' errors alone)."""
    if not len(errors):
        return float("nan")
    running = np.cumsum(errors) / np.arange(1, len(errors) + 1)
    last_of_tie = np.append(match_conf[1:] != match_conf[:-1], True)   # match_conf falls: the end of each tie
    conf_steps, running = match_conf[last_of_tie], running[last_of_tie]
    at_level = np.interp(level_conf[::-1], conf_steps[::-1], running[::-1])[::-1]
    nonzero = np.nonzero(level_conf)[0]
    first, last = round(100 * MIN_RECALL) + 1, (int(nonzero[-1]) if len(nonzero) else 0)
    if last < first:  # the highest recall reached is under MIN_RECALL: the mean over the matches
        return float(np.mean(errors))
    return float(np.mean(at_level[first:last + 1]))


def detection_scores(frames: list[tuple[list[TrueVehicle], list[Scored]]], keep_truth, keep_estimate) -> dict[str, float]:
    """nuScenes-style scores of one subset over all frames.

    Each frame is matched as a whole (every true vehicle, every estimate) at each threshold; then a match to a true
    vehicle in the subset (``keep_truth``) is a true positive, an unmatched estimate in the subset
    (``keep_estimate``: by its own range and evidence) a false positive, and an estimate matched to a vehicle
    outside the subset counts for neither. AP in %, per threshold and their mean (``ap``); ATE (m), ASE, AOE over
    360 deg (rad and deg) and modulo 180 deg (deg) at TP_THRESHOLD, recall-averaged; ``iou`` the mean BEV IoU of the
    matches at TP_THRESHOLD; ``center_err_median_m`` the median centre distance of those matches; ``recall`` and
    ``precision`` (%) of all estimates at TP_THRESHOLD; ``recall_at_p95`` (%) the recall at the lowest confidence
    threshold whose estimates are OPERATING_PRECISION precise (``recall_at_precision``)."""
    n_true = sum(keep_truth(t) for truth, _ in frames for t in truth)
    out = {k: float("nan") for k in DETECTION_METRICS}
    out["vehicles"] = float(n_true)
    if n_true == 0:
        out["estimates"] = float(sum(keep_estimate(e) for _, ests in frames for e in ests))
        return out
    aps = []
    for th in DIST_THRESHOLDS:
        ranked = []  # (confidence, is_tp, errors)
        for truth, ests in frames:
            boxes = [t.box for t in truth]
            for e, i in zip(ests, match_by_confidence(boxes, ests, th), strict=True):
                if i is not None and keep_truth(truth[i]):
                    ranked.append((e.confidence, 1, match_errors(boxes[i], e.box)))
                elif i is None and keep_estimate(e):
                    ranked.append((e.confidence, 0, None))
        ranked.sort(key=lambda r: -r[0])
        tp = np.array([r[1] for r in ranked], dtype=np.int64)
        conf = np.array([r[0] for r in ranked], dtype=np.float64)
        _, precision, level_conf = pr_curve(tp, conf, n_true)
        aps.append(100.0 * average_precision(precision))
        out[ap_key(th)] = aps[-1]
        if th == TP_THRESHOLD:
            matched = [r for r in ranked if r[1]]
            mconf = np.array([r[0] for r in matched], dtype=np.float64)
            for key in ("ate_m", "ase", "aoe_rad"):
                out[key] = tp_error(np.array([r[2][key] for r in matched]), mconf, level_conf)
            out["aoe_deg"] = math.degrees(out["aoe_rad"])
            out["aoe180_deg"] = math.degrees(tp_error(np.array([r[2]["aoe180_rad"] for r in matched]), mconf,
                                                      level_conf))
            out["iou"] = float(np.mean([r[2]["iou"] for r in matched])) if matched else float("nan")
            # the median, not nuScenes' recall average: the figure the population targets and earlier reports read
            out["center_err_median_m"] = float(np.median([r[2]["ate_m"] for r in matched])) if matched else float("nan")
            out["recall"] = 100.0 * len(matched) / n_true
            out["precision"] = 100.0 * len(matched) / len(ranked) if ranked else float("nan")
            out["estimates"] = float(len(ranked))
            out["recall_at_p95"] = 100.0 * recall_at_precision(tp, conf, n_true, OPERATING_PRECISION)
    out["ap"] = float(np.mean(aps))
    return out


def facing_agreement(test: list, preds: dict, match_iou: float = 0.5) -> dict | None:
    """How often the facing vectors of the predictions (the facing network's, or a detector's facing head's) point
    the right way: over the test split's vehicles with 3D truth that a predicted vehicle box matches (IoU >=
    ``match_iou``, greedily by score: ``deepword.metrics.match_boxes``), the
    share (%) whose facing vector lies within 90 deg of the true one (``deepword.facing``: image directions from rear
    to front), and how many there are. None when the predictions carry no facing vectors (no facing network and a
    detector without the head)."""
    from deepword.facing import box_facings, record_facing  # box_facings: what the heads learnt from
    from deepword.metrics import match_boxes

    right = total = 0
    for rec in test:
        pred = preds.get(rec.image)
        said = record_facing(pred) if pred is not None else {}
        if not said:
            continue
        truth = box_facings(rec)
        row = {int(b): i for i, b in enumerate(rec.box_ids)}
        for pred_id, true_id in match_boxes(rec, pred, match_iou).items():
            f, t = said.get(pred_id), truth[row[true_id]]
            if f is None or not np.isfinite(t).all():
                continue
            total += 1
            right += float(np.dot(f, t)) > 0
    return None if total == 0 else {"acc": 100.0 * right / total, "vehicles": float(total)}


def role_agreement(test: list, preds: dict, fused: dict, cameras: dict, prior, match_iou: float = 0.5) -> dict | None:
    """How often each way of naming a wheel's role (front / rear) is right, over the predicted relations that name a
    true relation with a known role (both boxes matched at IoU >= ``match_iou``: ``deepword.scoring.roles.true_roles``):
    the relation method's own roles (``network_acc``, a relation without one counts as wrong), the facing vector's
    (``facing_acc``: ``deepword.wheel_roles.facing_roles``, what ``deepword infer`` writes without a calibration) and
    the roles ``deepword infer`` writes with one (``acc``: from the fused footprint, else the facing vector, else the
    method's), with how many relations (``relations``) and the share the footprint decided (``footprint_share``).
    ``fused``: {frame: [(footprint, estimates)]} of the predictions' footprints. None where no relation qualifies."""
    from deepword.footprint import record_contacts
    from deepword.scoring.roles import true_roles
    from deepword.wheel_roles import front_rules, with_roles

    right = {"network": 0, "facing": 0, "shipped": 0}
    total = decided = 0
    for rec in test:
        pred = preds.get(rec.image)
        if pred is None or not pred.relations:
            continue
        judged = true_roles(rec, pred, match_iou)
        rules = front_rules(pred, fused.get(rec.frame_id, []), record_contacts(pred, cameras[rec.image], prior))
        (_, by_footprint), (_, by_facing) = rules
        shipped = {(v, w): r for v, w, r in with_roles(pred, rules).relations}
        for v, w, role in pred.relations:
            true_role = judged.get((v, w))
            if true_role is None:
                continue
            total += 1
            decided += (v, w) in by_footprint
            right["network"] += role == true_role
            right["facing"] += by_facing.get((v, w)) == true_role
            right["shipped"] += shipped[(v, w)] == true_role
    if total == 0:
        return None
    return {"acc": 100.0 * right["shipped"] / total, "network_acc": 100.0 * right["network"] / total,
            "facing_acc": 100.0 * right["facing"] / total, "footprint_share": 100.0 * decided / total,
            "relations": float(total)}
