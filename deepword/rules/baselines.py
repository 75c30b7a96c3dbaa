"""The logic-model baselines of docs/design.md §7, each with parameters fitted on the train split only.

- ``logic``: the paper's IoU rule. Each wheel goes to the vehicle whose box has the highest IoU with the
  wheel's box, if that IoU exceeds a threshold.
- ``logic_plus``: the strongest hand-written geometric rule we could make. Gates: the wheel lies mostly
  inside the vehicle box (containment share) and in its lower part. Cost: the wheel's bottom is level
  with the vehicle box's bottom (wheels touch the ground and bound a vehicle box from below, which
  separates a near vehicle from the one behind it), the Eq. 2 distance ratio and the wheel/vehicle size
  ratio are typical of true pairs, the wheel sits near the box's left or right end, containment. A
  Hungarian assignment with at most four wheels per vehicle and a "no owner" option at a fitted cost.
- ``prior``: each wheel goes to the vehicle with the highest Gaussian-mixture prior, above a threshold.

Couples: two wheels of the same predicted vehicle whose couple score passes a fitted threshold, greedily
best first, each wheel in at most one couple and at most two couples per vehicle (one per side); listed
in image x order (the image does not tell rear from front). ``logic`` and ``logic_plus`` score a couple by
how close its symmetric distance ratio is to the train couples' median; ``prior`` by the wheel-wheel prior.

Every method has ``name`` and ``predict(record) -> Record`` (same boxes, predicted relations and couples).
"""

from __future__ import annotations

import itertools
import random
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from deepword.geometry import box_centres, containment, pairwise_distance_ratio, pairwise_iou
from deepword.metrics import Counts, count_relations
from deepword.word_format import VEHICLE, WHEEL, Record

# the rules the evaluate stage fitted on train, by name (``baseline_params``): what ``deepword infer`` runs them with
BASELINES_FILE = "baselines.json"
MAX_WHEELS_PER_VEHICLE = 4
MAX_COUPLES_PER_VEHICLE = 2
_INFEASIBLE = 1e6
# the rules fitted on train, by name (each class registers itself with ``@rule``): what ``baselines.json`` and a
# bundle's end-to-end fallback name, ``baseline_params`` writes and ``baseline_from_params`` rebuilds
RULES: dict[str, type] = {}


def rule(cls: type) -> type:
    """Register a rule method class by its ``name``; the class gives ``to_params()`` (its fitted parameters as plain
    JSON) and ``from_params(params, priors)`` (the rule again from them)."""
    if cls.name in RULES:
        raise ValueError(f"rule method {cls.name!r} is registered twice")
    RULES[cls.name] = cls
    return cls


# --- shared pieces -------------------------------------------------------------------------------------

@dataclass
class Objects:
    """Indices of a record's vehicles and wheels (rows of ``rec.boxes``)."""

    rec: Record
    vehicles: np.ndarray
    wheels: np.ndarray

    @classmethod
    def of(cls, rec: Record) -> Objects:
        return cls(rec, np.flatnonzero(rec.class_ids == VEHICLE), np.flatnonzero(rec.class_ids == WHEEL))

    @property
    def v_xyxy(self) -> np.ndarray:
        return self.rec.xyxy[self.vehicles]

    @property
    def w_xyxy(self) -> np.ndarray:
        return self.rec.xyxy[self.wheels]


def symmetric_couple_ratio(obj: Objects) -> np.ndarray:
    """(W, W) geometric mean of the Eq. 2 ratio both ways (which wheel is the front one is unknown)."""
    r = pairwise_distance_ratio(obj.w_xyxy, obj.w_xyxy, obj.rec.width, obj.rec.height)
    return np.sqrt(r * r.T)


def pick_couples(owner: np.ndarray, score: np.ndarray, threshold: float) -> list[tuple[int, int]]:
    """Greedy couples (i, j) of wheel indices with the same owner and score >= threshold."""
    cand = [(score[i, j], i, j) for i, j in itertools.combinations(range(len(owner)), 2)
            if owner[i] >= 0 and owner[i] == owner[j] and score[i, j] >= threshold]
    used, per_vehicle, out = set(), {}, []
    for _, i, j in sorted(cand, key=lambda c: (-c[0], c[1], c[2])):
        if i in used or j in used or per_vehicle.get(owner[i], 0) >= MAX_COUPLES_PER_VEHICLE:
            continue
        used |= {i, j}
        per_vehicle[owner[i]] = per_vehicle.get(owner[i], 0) + 1
        out.append((i, j))
    return out


def as_prediction(obj: Objects, owner: np.ndarray, couples: list[tuple[int, int]]) -> Record:
    """A Record with the input boxes, ``owner`` (vehicle index per wheel, -1 none) and couples."""
    ids = obj.rec.box_ids
    relations = [(int(ids[obj.vehicles[v]]), int(ids[obj.wheels[w]]), None) for w, v in enumerate(owner) if v >= 0]
    cx = box_centres(obj.w_xyxy)[:, 0] if len(obj.wheels) else np.zeros(0)
    pairs = [tuple(int(ids[obj.wheels[k]]) for k in sorted((i, j), key=lambda k: cx[k])) for i, j in couples]
    return replace(obj.rec, boxes=obj.rec.boxes.copy(), relations=relations, wheel_pairs=pairs, source=None)


def argmax_owner(score: np.ndarray, threshold: float, strict: bool) -> np.ndarray:
    """(W, V) scores -> per wheel the best vehicle index if its score passes the threshold, else -1."""
    if score.shape[1] == 0:
        return np.full(score.shape[0], -1)
    best = score.argmax(axis=1)
    top = score[np.arange(len(best)), best]
    ok = top > threshold if strict else top >= threshold
    return np.where(ok, best, -1)


@dataclass
class CoupleRule:
    """Couple score = -|log(symmetric ratio) - centre|; a couple needs score >= -tolerance."""

    centre: float
    tolerance: float

    def couples(self, obj: Objects, owner: np.ndarray) -> list[tuple[int, int]]:
        if len(obj.wheels) < 2:
            return []
        score = -np.abs(np.log(np.maximum(symmetric_couple_ratio(obj), 1e-9)) - self.centre)
        return pick_couples(owner, score, -self.tolerance)


# --- the three methods ----------------------------------------------------------------------------------

@rule
@dataclass
class Logic:
    """The paper's IoU rule."""

    iou_threshold: float
    couple_rule: CoupleRule
    name: str = "logic"

    def to_params(self) -> dict:
        return {"iou_threshold": self.iou_threshold, "couple_rule": asdict(self.couple_rule)}

    @classmethod
    def from_params(cls, params: dict, priors=None) -> Logic:
        return cls(params["iou_threshold"], CoupleRule(**params["couple_rule"]))

    def owners(self, obj: Objects) -> np.ndarray:
        return argmax_owner(pairwise_iou(obj.w_xyxy, obj.v_xyxy), self.iou_threshold, strict=True)

    def predict(self, rec: Record) -> Record:
        obj = Objects.of(rec)
        owner = self.owners(obj)
        return as_prediction(obj, owner, self.couple_rule.couples(obj, owner))


@dataclass
class LogicPlusParams:
    """Gates and cost weights of ``logic_plus`` (fitted by coordinate-wise grid search on train)."""

    min_containment: float = 0.5
    min_height: float = 0.3   # wheel centre at least this far down the vehicle box (0 top, 1 bottom)
    w_bottom: float = 1.0     # |vehicle bottom - wheel bottom| / wheel height
    w_ratio: float = 0.5      # |log ratio - train median| / train spread
    w_size: float = 0.5       # |log(wheel h / vehicle h) - train median| / train spread
    w_end: float = 0.0        # distance of the wheel centre to the nearer box end / vehicle width
    w_contain: float = 1.0    # 1 - containment share
    none_cost: float = 4.0    # cost of leaving a wheel without owner


@dataclass(frozen=True)
class SearchGrids:
    """The values each baseline parameter is searched over on train (``eval.baseline_grids``)."""

    couple_tolerance: tuple[float, ...]    # CoupleRule tolerance (logic, logic_plus)
    logic_iou: tuple[float, ...]           # logic's IoU threshold
    prior_owner: tuple[float, ...]         # prior's owner threshold
    prior_couple: tuple[float, ...]        # prior's couple threshold
    logic_plus: dict[str, tuple[float, ...]]  # LogicPlusParams field -> values, searched coordinate-wise
    logic_plus_rounds: int                 # passes of the coordinate-wise search

    @classmethod
    def from_cfg(cls, grids) -> SearchGrids:
        values = lambda xs: tuple(float(x) for x in xs)  # noqa: E731
        return cls(values(grids.couple_tolerance), values(grids.logic_iou), values(grids.prior_owner),
                   values(grids.prior_couple),
                   {k: values(grids.logic_plus[k]) for k in logic_plus_search_order(grids.logic_plus)},
                   int(grids.logic_plus_rounds))


def logic_plus_search_order(names) -> list[str]:
    """``names`` in ``LogicPlusParams``' field order, the order ``fit_logic_plus`` visits them in whatever order a
    grid lists them: a coordinate search depends on its order, and the cache key reads the config with sorted keys,
    so two orders of the YAML must fit the same rule. A name that is no field is an error."""
    order = [f.name for f in fields(LogicPlusParams) if f.name in names]
    if unknown := sorted(set(names) - set(order)):
        raise ValueError(f"eval.baseline_grids.logic_plus: {unknown} are not LogicPlusParams fields "
                         f"(expected some of {[f.name for f in fields(LogicPlusParams)]})")
    return order


@dataclass
class PairStats:
    """Median and robust spread (IQR / 1.349) of a log feature over the train split's true pairs."""

    median: float
    spread: float

    @classmethod
    def of(cls, x: np.ndarray) -> PairStats:
        if not len(x):
            return cls(0.0, 1.0)
        q1, q2, q3 = np.percentile(x, [25, 50, 75])
        return cls(float(q2), float(max((q3 - q1) / 1.349, 1e-3)))

    def z(self, x: np.ndarray) -> np.ndarray:
        return np.abs(x - self.median) / self.spread


@dataclass
class PairFeatures:
    """Everything ``logic_plus`` looks at for each (wheel, vehicle): (W, V) arrays."""

    contain: np.ndarray
    height: np.ndarray
    bottom: np.ndarray
    log_ratio: np.ndarray
    log_size: np.ndarray
    end: np.ndarray

    @classmethod
    def of(cls, obj: Objects) -> PairFeatures:
        w, v = obj.w_xyxy[:, None, :], obj.v_xyxy[None, :, :]
        wh = np.maximum(w[..., 3] - w[..., 1], 1e-6)
        vh = np.maximum(v[..., 3] - v[..., 1], 1e-6)
        vw = np.maximum(v[..., 2] - v[..., 0], 1e-6)
        wx, wy = (w[..., 0] + w[..., 2]) / 2, (w[..., 1] + w[..., 3]) / 2
        ratio = pairwise_distance_ratio(obj.v_xyxy, obj.w_xyxy, obj.rec.width, obj.rec.height).T
        return cls(contain=containment(obj.w_xyxy, obj.v_xyxy),
                   height=(wy - v[..., 1]) / vh,
                   bottom=np.abs(v[..., 3] - w[..., 3]) / wh,
                   log_ratio=np.log(np.maximum(ratio, 1e-9)),
                   log_size=np.log(wh / vh),
                   end=np.clip(np.minimum(wx - v[..., 0], v[..., 2] - wx) / vw, 0, None))


def assign_with_capacity(cost: np.ndarray, none_cost: float) -> np.ndarray:
    """Minimum-cost owners: each vehicle takes at most four wheels, each wheel one vehicle or none."""
    n_w, n_v = cost.shape
    if n_w == 0:
        return np.zeros(0, dtype=int)
    none = np.full((n_w, n_w), _INFEASIBLE)
    np.fill_diagonal(none, none_cost)
    full = np.concatenate([np.repeat(cost, MAX_WHEELS_PER_VEHICLE, axis=1), none], axis=1)
    rows, cols = linear_sum_assignment(full)
    owner = np.full(n_w, -1)
    is_vehicle = cols < n_v * MAX_WHEELS_PER_VEHICLE
    owner[rows[is_vehicle]] = cols[is_vehicle] // MAX_WHEELS_PER_VEHICLE
    return owner


@rule
@dataclass
class LogicPlus:
    """Containment, lower part, bottom alignment, distance/size ratio and capacity-constrained assignment."""

    params: LogicPlusParams
    ratio_stats: PairStats
    size_stats: PairStats
    couple_rule: CoupleRule
    name: str = "logic_plus"

    def to_params(self) -> dict:
        return {"params": asdict(self.params), "ratio_stats": asdict(self.ratio_stats),
                "size_stats": asdict(self.size_stats), "couple_rule": asdict(self.couple_rule)}

    @classmethod
    def from_params(cls, params: dict, priors=None) -> LogicPlus:
        return cls(LogicPlusParams(**params["params"]), PairStats(**params["ratio_stats"]),
                   PairStats(**params["size_stats"]), CoupleRule(**params["couple_rule"]))

    def cost(self, f: PairFeatures) -> np.ndarray:
        p = self.params
        c = (p.w_bottom * np.minimum(f.bottom, 10) + p.w_ratio * np.minimum(self.ratio_stats.z(f.log_ratio), 10)
             + p.w_size * np.minimum(self.size_stats.z(f.log_size), 10) + p.w_end * f.end
             + p.w_contain * (1 - f.contain))
        feasible = (f.contain >= p.min_containment) & (f.height >= p.min_height)
        return np.where(feasible, c, _INFEASIBLE)

    def owners_from(self, f: PairFeatures) -> np.ndarray:
        return assign_with_capacity(self.cost(f), self.params.none_cost)

    def predict(self, rec: Record) -> Record:
        obj = Objects.of(rec)
        owner = self.owners_from(PairFeatures.of(obj))
        return as_prediction(obj, owner, self.couple_rule.couples(obj, owner))


@rule
@dataclass
class PriorMethod:
    """Highest wheel-vehicle prior above a threshold; couples by the wheel-wheel prior."""

    priors: object  # deepword.priors.Priors
    threshold: float
    couple_threshold: float
    name: str = "prior"

    def to_params(self) -> dict:
        return {"threshold": self.threshold, "couple_threshold": self.couple_threshold}

    @classmethod
    def from_params(cls, params: dict, priors=None) -> PriorMethod:
        if priors is None:
            raise ValueError("the prior baseline needs the priors (deepword.priors.load_priors)")
        return cls(priors, params["threshold"], params["couple_threshold"])

    def scores(self, obj: Objects) -> np.ndarray:
        ratio = pairwise_distance_ratio(obj.v_xyxy, obj.w_xyxy, obj.rec.width, obj.rec.height).T
        return self.priors.wheel_vehicle(ratio)

    def couple_scores(self, obj: Objects) -> np.ndarray:
        r = pairwise_distance_ratio(obj.w_xyxy, obj.w_xyxy, obj.rec.width, obj.rec.height)
        s = self.priors.wheel_wheel(r)
        return np.maximum(s, s.T)

    def predict(self, rec: Record) -> Record:
        obj = Objects.of(rec)
        owner = argmax_owner(self.scores(obj), self.threshold, strict=False)
        couples = pick_couples(owner, self.couple_scores(obj), self.couple_threshold) if len(obj.wheels) > 1 else []
        return as_prediction(obj, owner, couples)


# --- fitting on the train split -------------------------------------------------------------------------

@dataclass
class TrainImage:
    """A train record with its true owner per wheel index and the evaluated-wheel mask."""

    obj: Objects
    true_owner: np.ndarray
    evaluated: np.ndarray


def prepare_train(records: list[Record], min_box_px: float, max_images: int, seed: int) -> list[TrainImage]:
    """A seeded sample of at most ``max_images`` train records, with their truths as index arrays."""
    records = list(records)
    if len(records) > max_images:
        records = random.Random(seed).sample(records, max_images)
    out = []
    for rec in records:
        obj = Objects.of(rec)
        v_index = {int(rec.box_ids[i]): k for k, i in enumerate(obj.vehicles)}
        owner = rec.owner_of()
        true = np.array([v_index.get(owner.get(int(rec.box_ids[i]), -10**12), -1) for i in obj.wheels], dtype=int)
        wx = obj.w_xyxy
        short = np.minimum(wx[:, 2] - wx[:, 0], wx[:, 3] - wx[:, 1]) if len(wx) else np.zeros(0)
        out.append(TrainImage(obj, true, short >= min_box_px))
    return out


def train_counts(im: TrainImage, owners: np.ndarray | None = None,
                 couples: list[tuple[int, int]] | None = None) -> Counts:
    """§7 counts (``deepword.metrics``) of one train image's predicted owner indices and couples (wheel index
    pairs), on its ground-truth boxes and its evaluated wheels."""
    rec = im.obj.rec
    wheel_ids, vehicle_ids = rec.box_ids[im.obj.wheels], rec.box_ids[im.obj.vehicles]
    evaluated = {int(b) for b in wheel_ids[im.evaluated]}
    claimed = [] if owners is None else [(int(vehicle_ids[o]), int(w)) for w, o in zip(wheel_ids, owners, strict=True)
                                         if o >= 0]
    claimed_c = [(int(wheel_ids[a]), int(wheel_ids[b])) for a, b in couples or []]
    return count_relations(evaluated, {int(b) for b in wheel_ids} - evaluated, [(v, w) for v, w, _ in rec.relations],
                           rec.wheel_pairs, claimed, claimed_c)


def owner_objective(images: list[TrainImage], owners: list[np.ndarray]) -> float:
    """wheel_acc + image_acc (percent) of predicted owner indices: the fitting objective."""
    total = sum((train_counts(im, own) for im, own in zip(images, owners, strict=True)), Counts())
    metrics = total.percentages()
    return metrics["wheel_acc"] + metrics["image_acc"]


def couple_f1(images: list[TrainImage], couples: list[list[tuple[int, int]]]) -> float:
    """Couple F1 (percent) of couples given as wheel index pairs, against the train truth."""
    total = sum((train_counts(im, couples=c) for im, c in zip(images, couples, strict=True)), Counts())
    return total.percentages()["couple_f1"]


def fit_couple_rule(images: list[TrainImage], tolerances: Sequence[float]) -> CoupleRule:
    """Centre on the true couples' median log ratio; tolerance maximising couple F1 given true owners."""
    logs = []
    for im in images:
        if len(im.obj.wheels) < 2:
            continue
        r = symmetric_couple_ratio(im.obj)
        index = {int(b): k for k, b in enumerate(im.obj.rec.box_ids[im.obj.wheels])}
        logs += [np.log(max(r[index[a], index[b]], 1e-9)) for a, b in im.obj.rec.wheel_pairs]
    centre = float(np.median(logs)) if logs else 0.0
    best = None
    for tol in tolerances:
        rule = CoupleRule(centre, tol)
        f1 = couple_f1(images, [rule.couples(im.obj, im.true_owner) for im in images])
        if best is None or f1 > best[0]:
            best = (f1, rule)
    return best[1]


def fit_logic(images: list[TrainImage], couple_rule: CoupleRule, thresholds: Sequence[float]) -> Logic:
    """The IoU threshold maximising the train objective."""
    ious = [pairwise_iou(im.obj.w_xyxy, im.obj.v_xyxy) for im in images]
    best = None
    for thr in thresholds:
        score = owner_objective(images, [argmax_owner(s, thr, strict=True) for s in ious])
        if best is None or score > best[0]:
            best = (score, thr)
    return Logic(best[1], couple_rule)


def fit_logic_plus(images: list[TrainImage], couple_rule: CoupleRule, grid: dict[str, Sequence[float]],
                   rounds: int) -> LogicPlus:
    """Robust statistics of the true pairs, then coordinate-wise grid search of the gates and weights
    (``logic_plus_search_order``)."""
    order = logic_plus_search_order(grid)
    feats = [PairFeatures.of(im.obj) for im in images]
    ratio_logs, size_logs = [], []
    for im, f in zip(images, feats, strict=True):
        rows = np.flatnonzero(im.true_owner >= 0)
        ratio_logs.append(f.log_ratio[rows, im.true_owner[rows]])
        size_logs.append(f.log_size[rows, im.true_owner[rows]])
    model = LogicPlus(LogicPlusParams(), PairStats.of(np.concatenate(ratio_logs) if ratio_logs else np.zeros(0)),
                      PairStats.of(np.concatenate(size_logs) if size_logs else np.zeros(0)), couple_rule)

    def objective(params: LogicPlusParams) -> float:
        trial = replace(model, params=params)
        return owner_objective(images, [trial.owners_from(f) for f in feats])

    best_params, best_score = model.params, objective(model.params)
    for _ in range(rounds):
        for name in order:
            for value in grid[name]:
                params = replace(best_params, **{name: value})
                score = objective(params)
                if score > best_score + 1e-9:
                    best_params, best_score = params, score
    return replace(model, params=best_params)


def fit_prior(images: list[TrainImage], priors, thresholds: Sequence[float],
              couple_thresholds: Sequence[float]) -> PriorMethod:
    """Owner and couple thresholds on the priors maximising the train objective and couple F1."""
    method = PriorMethod(priors, 0.0, 0.0)
    scores = [method.scores(im.obj) for im in images]
    best = None
    for thr in thresholds:
        score = owner_objective(images, [argmax_owner(s, thr, strict=False) for s in scores])
        if best is None or score > best[0]:
            best = (score, thr)
    couple_scores = [method.couple_scores(im.obj) for im in images]
    best_c = None
    for thr in couple_thresholds:
        f1 = couple_f1(images, [pick_couples(im.true_owner, s, thr) for im, s in zip(images, couple_scores, strict=True)])
        if best_c is None or f1 > best_c[0]:
            best_c = (f1, thr)
    return PriorMethod(priors, best[1], best_c[1])


# --- persistence: fitted parameters as JSON, so inference can rebuild each method -------------------------

def baseline_params(method) -> dict:
    """The fitted parameters of a baseline (a ``RULES`` method) as plain JSON."""
    kind = RULES.get(getattr(method, "name", None))
    if kind is None or not isinstance(method, kind):
        raise TypeError(f"not a baseline: {method!r}")
    return method.to_params()


def baseline_from_params(name: str, params: dict, priors=None):
    """Rebuild a baseline from ``baseline_params`` output (``prior`` also needs the loaded priors)."""
    if name not in RULES:
        raise ValueError(f"unknown baseline {name!r}; have {', '.join(RULES)}")
    return RULES[name].from_params(params, priors)
