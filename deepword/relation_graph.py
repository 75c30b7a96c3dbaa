"""Graph inputs of the DeepWORD relation network (docs/design.md §6), built once per image and cached per split.

Per image, every annotated object becomes a node:
- its box crop with a context margin, resized to S x S (OpenCV, no RoI Align), kept as uint8 RGB;
- its normalised box x1/W, y1/H, x2/W, y2/H, later broadcast to four constant planes (``node_tensor``);
- its class and validity (padding to ``max_objects``; ``small_mask_px`` masks small objects).
Edges: the adjacency holds the Gaussian-mixture priors of wheel-vehicle pairs (both directions) and
wheel-wheel pairs, self-loops for valid nodes, zeros for vehicle-vehicle pairs and masked nodes. A
*candidate* pair is a wheel-vehicle or wheel-wheel pair of two valid nodes whose prior reaches
``min_prior``; only candidates are trained on and only candidates can be predicted.
Targets: 0/1 ownership (wheel-vehicle, symmetric), couples (wheel-wheel, symmetric) and each wheel's
role (1 front, 0 rear, -1 unknown) from the relation's role or the couple order (rear first).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from deepword.geometry import pairwise_distance_ratio
from deepword.metrics import evaluated_mask
from deepword.word_format import VEHICLE, WHEEL, Record

PriorFn = Callable[[np.ndarray], np.ndarray]
ADJACENCY_MODES = ("prior", "uniform")
PAD_CLASS = -1


@dataclass(frozen=True)
class InputConfig:
    """What decides the graph inputs (and thus the cache entry of a split)."""

    input_size: int = 56
    margin: float = 0.2
    min_crop_px: float = 0.0
    max_objects: int = 32
    small_mask_px: float = 0.0
    adjacency: str = "prior"
    min_prior: float = 0.0

    def __post_init__(self):
        if self.adjacency not in ADJACENCY_MODES:
            raise ValueError(f"relation.adjacency must be one of {ADJACENCY_MODES}, got {self.adjacency!r}")
        if self.input_size < 8:
            raise ValueError(f"relation.backbone.input_size must be >= 8, got {self.input_size}")
        if self.max_objects < 1:
            raise ValueError(f"relation.max_objects must be >= 1, got {self.max_objects}")
        if self.margin < 0:
            raise ValueError(f"relation.margin must be >= 0, got {self.margin}")
        if self.min_crop_px < 0:
            raise ValueError(f"relation.min_crop_px must be >= 0, got {self.min_crop_px}")

    @classmethod
    def from_cfg(cls, rel) -> InputConfig:
        return cls(input_size=int(rel.backbone.input_size), margin=float(rel.margin),
                   min_crop_px=float(rel.min_crop_px), max_objects=int(rel.max_objects),
                   small_mask_px=float(rel.small_mask_px), adjacency=str(rel.adjacency),
                   min_prior=float(rel.min_prior))


# --- crops ------------------------------------------------------------------------------------------

def crop_object(rgb: np.ndarray, box: Sequence[float], size: int, margin: float, min_px: float = 0.0) -> np.ndarray:
    """The box grown by ``margin`` x its width/height on each side, then about its centre to at least
    ``min_px`` pixels wide and high, resized to size x size (uint8 RGB). Parts of the grown box outside the
    image stay black, so the box keeps its place in the crop."""
    import cv2  # deferred: OpenCV loads only when crops are built

    height, width = rgb.shape[:2]
    x1, y1, x2, y2 = (float(v) for v in box[:4])
    mx = max(margin * (x2 - x1), (min_px - (x2 - x1)) / 2)
    my = max(margin * (y2 - y1), (min_px - (y2 - y1)) / 2)
    gx1, gy1, gx2, gy2 = x1 - mx, y1 - my, x2 + mx, y2 + my
    sx, sy = size / (gx2 - gx1), size / (gy2 - gy1)
    cx1, cy1 = max(math.floor(gx1), 0), max(math.floor(gy1), 0)
    cx2, cy2 = min(math.ceil(gx2), width), min(math.ceil(gy2), height)
    canvas = np.zeros((size, size, 3), dtype=np.uint8)
    if cx2 <= cx1 or cy2 <= cy1:
        return canvas
    dx1, dy1 = _clamp_round((cx1 - gx1) * sx, size), _clamp_round((cy1 - gy1) * sy, size)
    dx2, dy2 = _clamp_round((cx2 - gx1) * sx, size), _clamp_round((cy2 - gy1) * sy, size)
    dx2, dy2 = max(dx2, dx1 + 1), max(dy2, dy1 + 1)
    dx1, dy1 = min(dx1, size - 1), min(dy1, size - 1)
    dx2, dy2 = min(dx2, size), min(dy2, size)
    patch = rgb[cy1:cy2, cx1:cx2]
    # INTER_AREA anti-aliases the large downscales of near vehicles; it equals linear when upscaling
    canvas[dy1:dy2, dx1:dx2] = cv2.resize(patch, (dx2 - dx1, dy2 - dy1), interpolation=cv2.INTER_AREA)
    return canvas


def _clamp_round(v: float, size: int) -> int:
    return int(min(max(round(v), 0), size))


def crop_objects(rgb: np.ndarray, xyxy: np.ndarray, size: int, margin: float, min_px: float = 0.0) -> np.ndarray:
    """Every box's crop: (N, 4) boxes -> (N, 3, size, size) uint8, channels first."""
    crops = np.zeros((len(xyxy), 3, size, size), dtype=np.uint8)
    for i, box in enumerate(xyxy):
        crops[i] = crop_object(rgb, box, size, margin, min_px).transpose(2, 0, 1)
    return crops


def normalised_boxes(xyxy: np.ndarray, width: float, height: float) -> np.ndarray:
    """x1/W, y1/H, x2/W, y2/H per box: (N, 4) float32."""
    scale = np.array([width, height, width, height], dtype=np.float64)
    return (np.asarray(xyxy, dtype=np.float64).reshape(-1, 4) / scale).astype(np.float32)


def node_tensor(crops, coords, channels_last: bool = False):
    """The S x S x 7 node input of docs/design.md §6, channels first: RGB in [0, 1] then four constant planes.
    crops (..., 3, S, S) uint8 tensor, coords (..., 4) -> (..., 7, S, S) float32 tensor. ``channels_last`` (crops
    (K, 3, S, S)): the same values laid out NHWC, as the backbone trains, written in place rather than converted
    after (the conversion was 3 % of a relation training step on a bf16 host)."""
    import torch

    rgb = crops.to(torch.float32) / 255.0
    planes = coords.to(torch.float32)[..., None, None]
    if channels_last:
        out = torch.empty((len(crops), 7, *crops.shape[-2:]), device=crops.device, memory_format=torch.channels_last)
        out[:, :3], out[:, 3:] = rgb, planes
        return out
    return torch.cat([rgb, planes.expand(*coords.shape, *crops.shape[-2:])], dim=-3)


# --- adjacency, candidates, targets (vectorised per image) -----------------------------------------

def node_validity(xyxy: np.ndarray, small_mask_px: float) -> np.ndarray:
    """Objects kept in the graph: all, or (``small_mask``) those whose shorter side is >= small_mask_px."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    short = np.minimum(xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1])
    return short >= small_mask_px if small_mask_px > 0 else np.ones(len(xyxy), dtype=bool)


def pair_priors(xyxy: np.ndarray, classes: np.ndarray, width: float, height: float,
                wheel_vehicle: PriorFn, wheel_wheel: PriorFn) -> np.ndarray:
    """(N, N) prior of every node pair: wheel-vehicle (symmetric, A = vehicle, B = wheel), wheel-wheel
    (symmetric: rear and front are unknown at inference, so the likelier order counts), 0 elsewhere."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    n = len(xyxy)
    out = np.zeros((n, n), dtype=np.float64)
    if n == 0:
        return out
    ratio = pairwise_distance_ratio(xyxy, xyxy, width, height)  # ratio[a, b]: A = a, B = b
    is_wheel, is_vehicle = classes == WHEEL, classes == VEHICLE
    wv = is_vehicle[:, None] & is_wheel[None, :]  # rows vehicles (A), columns wheels (B)
    if wv.any():
        out[wv] = np.asarray(wheel_vehicle(ratio[wv]), dtype=np.float64)
        out = np.maximum(out, out.T)
    ww = is_wheel[:, None] & is_wheel[None, :] & ~np.eye(n, dtype=bool)
    if ww.any():
        prior_ww = np.zeros((n, n), dtype=np.float64)
        prior_ww[ww] = np.asarray(wheel_wheel(ratio[ww]), dtype=np.float64)
        out = np.where(ww, np.maximum(prior_ww, prior_ww.T), out)
    return np.clip(out, 0.0, 1.0)


def candidate_pairs(classes: np.ndarray, valid: np.ndarray, priors: np.ndarray, min_prior: float) -> np.ndarray:
    """(N, N) bool: wheel-vehicle (either order) or wheel-wheel pairs of two valid, distinct nodes whose
    prior reaches ``min_prior`` (0: every such pair; ablation fewer_neg raises it)."""
    is_wheel, is_vehicle = classes == WHEEL, classes == VEHICLE
    both_valid = valid[:, None] & valid[None, :]
    wv = (is_wheel[:, None] & is_vehicle[None, :]) | (is_vehicle[:, None] & is_wheel[None, :])
    ww = is_wheel[:, None] & is_wheel[None, :] & ~np.eye(len(classes), dtype=bool)
    cand = (wv | ww) & both_valid
    return cand & (priors >= min_prior) if min_prior > 0 else cand


def adjacency(priors: np.ndarray, cand: np.ndarray, valid: np.ndarray, mode: str) -> np.ndarray:
    """Edge weights: the prior (mode ``prior``) or 1 (``uniform``, ablation no_prior) on candidate pairs,
    1 on the self-loop of every valid node, 0 elsewhere (vehicle-vehicle, masked and padded nodes)."""
    weights = priors if mode == "prior" else np.ones_like(priors)
    adj = np.where(cand, weights, 0.0)
    adj[np.diag_indices(len(valid))] = valid.astype(np.float64)
    return adj


def relation_targets(rec: Record) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """0/1 ownership (N, N), 0/1 couples (N, N), both symmetric, and roles (N,) 1 front, 0 rear, -1 unknown."""
    n = len(rec.boxes)
    index = {int(b): i for i, b in enumerate(rec.box_ids)}
    owner = np.zeros((n, n), dtype=np.uint8)
    couple = np.zeros((n, n), dtype=np.uint8)
    role = np.full(n, -1, dtype=np.int8)
    for v, w, r in rec.relations:
        owner[index[v], index[w]] = owner[index[w], index[v]] = 1
        if r is not None:
            role[index[w]] = 1 if r == "front" else 0
    for rear, front in rec.wheel_pairs:
        couple[index[rear], index[front]] = couple[index[front], index[rear]] = 1
        for box_id, value in ((rear, 0), (front, 1)):  # the couple order names roles a relation left out
            if role[index[box_id]] < 0:
                role[index[box_id]] = value
    return owner, couple, role


@dataclass
class ImageGraph:
    """One image's unpadded node data and edges."""

    crops: np.ndarray    # (n, 3, S, S) uint8
    coords: np.ndarray   # (n, 4) float32
    classes: np.ndarray  # (n,) int8
    valid: np.ndarray    # (n,) bool
    adj: np.ndarray      # (n, n) float32
    cand: np.ndarray     # (n, n) bool


def mirror_coords(coords):
    """(n, 4) normalised boxes (x1, y1, x2, y2; numpy or torch) of the image mirrored left-right, a new array:
    x1' = 1 - x2, x2' = 1 - x1."""
    out = coords[:, [2, 1, 0, 3]]   # advanced indexing copies, in numpy and torch alike
    out[:, [0, 2]] = 1.0 - out[:, [0, 2]]
    return out


def mirrored(graph: ImageGraph) -> ImageGraph:
    """The graph of the image mirrored left-right: crops flipped, x coordinates mirrored; classes, validity,
    adjacency and candidates as they are (the pair priors see distances and size ratios, not sides). What
    ``relation.train.hflip`` trains on, and what ``relation.decode.flip_average`` scores a second time."""
    return replace(graph, crops=np.ascontiguousarray(graph.crops[..., ::-1]), coords=mirror_coords(graph.coords))


def subgraph(graph: ImageGraph, rows: np.ndarray) -> ImageGraph:
    """The graph of a subset of its boxes (``rows``, in order): every node field and pair field is a function of its
    own box or pair only, so it is the whole graph with the other nodes' rows and columns removed."""
    rows = np.asarray(rows, dtype=int)
    pairs = np.ix_(rows, rows)
    return ImageGraph(crops=graph.crops[rows], coords=graph.coords[rows], classes=graph.classes[rows],
                      valid=graph.valid[rows], adj=graph.adj[pairs], cand=graph.cand[pairs])


def build_graph(rec: Record, rgb: np.ndarray, cfg: InputConfig, wheel_vehicle: PriorFn,
                wheel_wheel: PriorFn) -> ImageGraph:
    """Nodes and edges of one image from its boxes (annotated or detected) and its RGB image."""
    classes = rec.class_ids.astype(np.int8)
    valid = node_validity(rec.xyxy, cfg.small_mask_px)
    priors = pair_priors(rec.xyxy, classes, rec.width, rec.height, wheel_vehicle, wheel_wheel)
    cand = candidate_pairs(classes, valid, priors, cfg.min_prior)
    return ImageGraph(crops=crop_objects(rgb, rec.xyxy, cfg.input_size, cfg.margin, cfg.min_crop_px),
                      coords=normalised_boxes(rec.xyxy, rec.width, rec.height), classes=classes, valid=valid,
                      adj=adjacency(priors, cand, valid, cfg.adjacency).astype(np.float32), cand=cand)


# --- a split's padded arrays ------------------------------------------------------------------------

@dataclass
class SplitInputs:
    """All graphs of a split: crops packed (objects of image i at offsets[i]:offsets[i+1]), the rest padded
    to max_objects. Padded nodes have class -1, valid False and all-zero rows and columns."""

    crops: np.ndarray       # (M, 3, S, S) uint8, M = total object count
    offsets: np.ndarray     # (I + 1,) int64
    coords: np.ndarray      # (I, N, 4) float32
    classes: np.ndarray     # (I, N) int8
    valid: np.ndarray       # (I, N) bool
    adj: np.ndarray         # (I, N, N) float32
    cand: np.ndarray        # (I, N, N) bool
    owner: np.ndarray       # (I, N, N) uint8
    couple: np.ndarray      # (I, N, N) uint8
    role: np.ndarray        # (I, N) int8
    evaluated: np.ndarray   # (I, N) bool: the wheels validation scores, those evaluation scores (docs/design.md §7)
    images: np.ndarray      # (I,) str

    def __len__(self) -> int:
        return len(self.images)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **{k: getattr(self, k) for k in self.__dataclass_fields__})
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> SplitInputs:
        with np.load(path, allow_pickle=False) as z:
            return cls(**{k: z[k] for k in cls.__dataclass_fields__})


def check_object_counts(records: Sequence[Record], max_objects: int) -> None:
    """Fail before any training when an image has more objects than the padded graph can hold."""
    for rec in records:
        if len(rec.boxes) > max_objects:
            file, line = rec.source or ("<records>", 0)
            raise ValueError(f"{file}:{line}: image {rec.image!r} has {len(rec.boxes)} objects, more than "
                             f"relation.max_objects={max_objects}; raise relation.max_objects")


def build_split(records: Sequence[Record], load_rgb: Callable[[Record], np.ndarray], cfg: InputConfig,
                wheel_vehicle: PriorFn, wheel_wheel: PriorFn, min_box_px: float = 0.0, threads: int = 1) -> SplitInputs:
    """Graphs and targets of every record, padded to cfg.max_objects; the evaluated wheels are those whose
    shorter box side is at least ``min_box_px`` (``eval.min_box_px``). ``threads`` images are decoded and cropped at
    a time (OpenCV releases the GIL; decoding is most of the work): the same arrays in the same order."""
    check_object_counts(records, cfg.max_objects)

    def graph(rec: Record) -> ImageGraph:   # the decoded image is dropped once its crops are cut
        return build_graph(rec, load_rgb(rec), cfg, wheel_vehicle, wheel_wheel)

    n_img, n = len(records), cfg.max_objects
    coords = np.zeros((n_img, n, 4), dtype=np.float32)
    classes = np.full((n_img, n), PAD_CLASS, dtype=np.int8)
    valid = np.zeros((n_img, n), dtype=bool)
    adj = np.zeros((n_img, n, n), dtype=np.float32)
    cand = np.zeros((n_img, n, n), dtype=bool)
    owner = np.zeros((n_img, n, n), dtype=np.uint8)
    couple = np.zeros((n_img, n, n), dtype=np.uint8)
    role = np.full((n_img, n), -1, dtype=np.int8)
    evaluated = np.zeros((n_img, n), dtype=bool)
    crops, offsets = [], [0]
    with ThreadPoolExecutor(max(1, threads)) as pool:
        graphs = list(pool.map(graph, records))
    for i, (rec, g) in enumerate(zip(records, graphs, strict=True)):
        k = len(g.classes)
        crops.append(g.crops)
        offsets.append(offsets[-1] + k)
        coords[i, :k], classes[i, :k], valid[i, :k] = g.coords, g.classes, g.valid
        adj[i, :k, :k], cand[i, :k, :k] = g.adj, g.cand
        owner[i, :k, :k], couple[i, :k, :k], role[i, :k] = relation_targets(rec)
        evaluated[i, :k] = evaluated_mask(rec.xyxy, rec.class_ids, min_box_px)
    size = cfg.input_size
    packed = np.concatenate(crops) if crops else np.zeros((0, 3, size, size), dtype=np.uint8)
    return SplitInputs(crops=packed, offsets=np.asarray(offsets, dtype=np.int64), coords=coords,
                       classes=classes, valid=valid, adj=adj, cand=cand, owner=owner, couple=couple, role=role,
                       evaluated=evaluated,
                       images=np.asarray([r.image for r in records], dtype=str))
