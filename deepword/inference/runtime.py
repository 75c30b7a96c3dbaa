"""The shipped models in onnxruntime, without torch: what the evaluate stage's DeepWORD and detected-box
rows and ``deepword infer`` run.

An export stage directory (the *bundle*) holds everything inference needs, so nothing upstream must be
present at inference time::

    export.json            input and decoding settings, detector preprocessing, operating point and footprint point,
                           the end-to-end method and the rule it falls back on (fitted on train), file names, metrics
    priors.json            the Gaussian-mixture priors (adjacency of the graph)
    relation_static.onnx   objects padded to max_objects (static N; batch dynamic): for embedded runtimes
    relation_dynamic.onnx  batch and object count dynamic
    relation_int8.onnx     INT8 (onnxruntime dynamic quantisation of relation_dynamic.onnx)
    detector.onnx          CenterNet + decoding, dynamic batch: images -> (B, K, 6) detections; absent, with
                           export.json "detector": null, when the run left the detector out (pipeline.skip)
    facing.onnx            the facing network, vehicle crops -> which way each front lies (deepword.inference.
                           facing_net); absent, with "facing": null, without one (no 3D truth to learn from)

Evaluation and inference run the dynamic-N models, so every image is run at its real object count (the
static model gives the same scores within the parity tolerance; both are checked against PyTorch).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from deepword.detection.letterbox import preprocess
from deepword.detection.records import detections_to_record, renumbered
from deepword.inference.decode import decode_couples, decode_owners, prediction_record
from deepword.priors import load_priors
from deepword.relation_graph import InputConfig, build_graph, mirrored
from deepword.rules.baselines import baseline_from_params
from deepword.rules.fallback import FALLBACKS, ClaimFallback
from deepword.word_format import Record, load_image

BUNDLE_FILE = "export.json"
PRIORS_FILE = "priors.json"
RELATION_FILES = {"static": "relation_static.onnx", "dynamic": "relation_dynamic.onnx", "int8": "relation_int8.onnx"}
DETECTOR_FILE = "detector.onnx"
RELATION_INPUTS = ("crops", "coords", "adj", "cand")
RELATION_OUTPUTS = ("owner", "couple", "front")
DETECTOR_INPUT = "images"
# the detector graph's outputs by its box regression (detector.regression); the runtime reads "detections"
DETECTOR_OUTPUTS = {"centernet": ("heatmap", "wh", "reg", "detections"), "ttfnet": ("heatmap", "ltrb", "detections")}


def detector_outputs(regression: str, facing: bool) -> tuple[str, ...]:
    """The detector graph's output names: ``DETECTOR_OUTPUTS``' maps, the facing map after them with the facing head."""
    names = DETECTOR_OUTPUTS[regression]
    return (*names[:-1], "facing", names[-1]) if facing else names
# Which relation model a method name runs (evaluate rows and ``deepword infer --method``).
METHOD_VARIANTS = {"deepword": "dynamic", "deepword_int8": "int8"}


def ort_session(path: str | os.PathLike, threads: int):
    """An onnxruntime CPU session with a fixed intra-op thread count (one inter-op thread: sequential
    graphs), so latencies are comparable and recorded."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def read_bundle(bundle_dir: str | os.PathLike) -> dict:
    """``export.json`` of an export stage directory, with a clear error when it is not one."""
    path = Path(bundle_dir) / BUNDLE_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found; {bundle_dir} is not an export stage output")
    return json.loads(path.read_text())


# --- relation ---------------------------------------------------------------------------------------

def pad_graphs(graphs: Sequence, size: int, n: int | None = None,
               crops: bool = True) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Graphs (``deepword.relation_graph.ImageGraph``, crops ``size`` x ``size``) -> the network's feed,
    padded to ``n`` objects (default: the largest graph), and the (B, n) classes (-1 for padding). ``crops=False``:
    without the crops (for a model whose backbone features are computed elsewhere)."""
    n = max([len(g.classes) for g in graphs] + [1]) if n is None else n
    b = len(graphs)
    # in the order of RELATION_INPUTS: some callers pass the feed's values positionally
    feed = {"crops": np.zeros((b, n, 3, size, size), np.uint8)} if crops else {}
    feed |= {"coords": np.zeros((b, n, 4), np.float32), "adj": np.zeros((b, n, n), np.float32),
             "cand": np.zeros((b, n, n), np.float32)}
    classes = np.full((b, n), -1, np.int64)
    for i, g in enumerate(graphs):
        k = len(g.classes)
        if k > n:
            raise ValueError(f"a graph has {k} objects, more than the model's {n}")
        if crops:
            feed["crops"][i, :k] = g.crops
        feed["coords"][i, :k] = g.coords
        feed["adj"][i, :k, :k], feed["cand"][i, :k, :k] = g.adj, g.cand
        classes[i, :k] = g.classes
    return feed, classes


class OnnxRelation:
    """DeepWORD relations with an exported relation model: graph building as in training
    (``deepword.relation_graph.build_graph``), scores from onnxruntime, decisions as in
    ``stages.relation.decode`` and records as in ``stages.relation.predict``."""

    def __init__(self, bundle_dir: str | os.PathLike, variant: str = "dynamic", threads: int = 1):
        if variant not in RELATION_FILES:
            raise ValueError(f"unknown relation model variant {variant!r}; have {sorted(RELATION_FILES)}")
        bundle_dir = Path(bundle_dir)
        meta = read_bundle(bundle_dir)["relation"]
        self.variant = variant
        self.inputs = InputConfig(**meta["inputs"])
        self.threshold = float(meta["decode"]["threshold"])
        self.one_owner = bool(meta["decode"]["one_owner"])
        self.has_roles = bool(meta["has_roles"])
        self.min_containment = float(meta["decode"].get("min_containment", 0.0))
        # score each graph and its mirror image and decide on the mean (relation.decode.flip_average)
        self.flip_average = bool(meta["decode"].get("flip_average", False))
        self.priors = load_priors(bundle_dir / PRIORS_FILE)
        self.session = ort_session(bundle_dir / RELATION_FILES[variant], threads)
        self.static_n = self.inputs.max_objects if variant == "static" else None

    def graph(self, rec: Record, rgb: np.ndarray):
        return build_graph(rec, rgb, self.inputs, self.priors.wheel_vehicle, self.priors.wheel_wheel)

    def scores(self, graphs: Sequence) -> tuple[np.ndarray, ...]:
        """(owner, couple, front, classes, cand, coords) for a batch of graphs; with ``flip_average`` the
        scores are the mean of the graphs' and their mirror images' (test-time augmentation by the flip the
        network trained with: decisions no longer depend on which way the image faces)."""
        feed, classes = pad_graphs(graphs, self.inputs.input_size, self.static_n)
        owner, couple, front = self.session.run(list(RELATION_OUTPUTS), feed)
        if self.flip_average:
            flipped, _ = pad_graphs([mirrored(g) for g in graphs], self.inputs.input_size, self.static_n)
            owner_m, couple_m, front_m = self.session.run(list(RELATION_OUTPUTS), flipped)
            owner, couple, front = (owner + owner_m) / 2, (couple + couple_m) / 2, (front + front_m) / 2
        return owner, couple, front, classes, feed["cand"], feed["coords"]

    def predict_many(self, records: Sequence[Record], load_rgb: Callable[[Record], np.ndarray],
                     batch_size: int = 16) -> list[Record]:
        out = []
        for start in range(0, len(records), batch_size):
            chunk = records[start:start + batch_size]
            out += self.predict_graphs(chunk, [self.graph(r, load_rgb(r)) for r in chunk])
        return out

    def predict_graphs(self, records: Sequence[Record], graphs: Sequence) -> list[Record]:
        """Records with decided relations, from their already built graphs (one batch)."""
        return self.decide(records, self.scores(graphs))

    def decide(self, records: Sequence[Record], scores: tuple[np.ndarray, ...]) -> list[Record]:
        """Records with the relations decided from ``scores``: what ``scores`` returns for their graphs."""
        owner, couple, front, classes, cand, coords = scores
        pred_owner = decode_owners(owner, classes, cand, self.threshold, self.one_owner, coords, self.min_containment)
        pred_couple = decode_couples(couple, classes, cand, self.threshold)
        return [prediction_record(rec, pred_owner[i], pred_couple[i], front[i], self.has_roles)
                for i, rec in enumerate(records)]


class DeepwordMethod:
    """An evaluate row / inference method: ``predict(record) -> Record``, reading images with ``load_rgb``."""

    def __init__(self, name: str, relation: OnnxRelation, load_rgb: Callable[[Record], np.ndarray]):
        self.name, self.relation, self.load_rgb = name, relation, load_rgb

    def predict(self, rec: Record) -> Record:
        return self.relation.predict_many([rec], self.load_rgb)[0]


def deepword_method(name: str, bundle_dir: str | os.PathLike, root: str | os.PathLike, threads: int = 1,
                    load_rgb: Callable[[Record], np.ndarray] | None = None) -> DeepwordMethod:
    """``deepword`` / ``deepword_int8`` on records of the dataset at ``root`` (or images from ``load_rgb``)."""
    relation = OnnxRelation(bundle_dir, METHOD_VARIANTS[name], threads)
    return DeepwordMethod(name, relation, load_rgb or (lambda rec: load_image(root, rec)))


# --- the bundle's end-to-end method -------------------------------------------------------------------

class NoRuleError(LookupError):
    """The bundle holds no fitted rule of that name (it was exported before ``export.end_to_end`` existed)."""


def end_to_end_method(bundle_dir: str | os.PathLike) -> str:
    """The method the bundle ships for detected boxes (``export.end_to_end.method``): the one its detector's
    operating point was chosen by; ``deepword`` for a bundle exported before the setting existed."""
    return (read_bundle(bundle_dir).get("end_to_end") or {}).get("method", "deepword")


def bundle_rule(bundle_dir: str | os.PathLike, name: str):
    """A hand-written rule the export stage fitted on train and stored in the bundle (``logic``: the paper's IoU
    rule), as an object with ``predict(record) -> Record``."""
    rules = (read_bundle(bundle_dir).get("end_to_end") or {}).get("rules") or {}
    if name not in rules:
        raise NoRuleError(f"{Path(bundle_dir) / BUNDLE_FILE}: no fitted {name!r} rule (exported before bundles held "
                          "one)")
    return baseline_from_params(name, rules[name])


def bundle_method(name: str, bundle_dir: str | os.PathLike, root: str | os.PathLike, threads: int = 1,
                  load_rgb: Callable[[Record], np.ndarray] | None = None):
    """A method the bundle alone can run: ``deepword``, ``deepword_int8``, or a ``FALLBACKS`` method
    (``deepword_then_logic``) whose fallback rule the bundle holds (``NoRuleError`` when it does not)."""
    if name in METHOD_VARIANTS:
        return deepword_method(name, bundle_dir, root, threads, load_rgb)
    if name not in FALLBACKS:
        raise ValueError(f"{name!r} is not a method of the bundle; have {sorted([*METHOD_VARIANTS, *FALLBACKS])}")
    primary, fallback = FALLBACKS[name]
    return ClaimFallback(bundle_method(primary, bundle_dir, root, threads, load_rgb), bundle_rule(bundle_dir, fallback),
                         name)


# --- detector ---------------------------------------------------------------------------------------

def kept_masks(record: Record, thresholds: np.ndarray, min_sides: np.ndarray) -> np.ndarray:
    """Which boxes each of P operating points keeps, (P, boxes): a score of at least the point's threshold for the
    box's class (``thresholds`` (P, classes)) and a shorter side of at least its minimum (``min_sides`` (P, classes),
    image pixels). The operating-point search asks this of thousands of points at once."""
    classes = record.class_ids.astype(int)
    xyxy = record.xyxy
    shorter = np.minimum(xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1])
    thresholds, min_sides = np.asarray(thresholds, dtype=np.float64), np.asarray(min_sides, dtype=np.float64)
    return (record.scores[None, :] >= thresholds[:, classes]) & (shorter[None, :] >= min_sides[:, classes])


def kept_mask(record: Record, thresholds: Sequence[float], min_sides: Sequence[float] | None = None) -> np.ndarray:
    """Which boxes reach their class's score threshold (``thresholds[class_id]``) and, with ``min_sides``, their
    class's minimum shorter side (image pixels): ``kept_masks`` at one point (no minimum side: -inf)."""
    sides = np.full(len(thresholds), -np.inf) if min_sides is None else min_sides
    return kept_masks(record, np.asarray(thresholds, dtype=np.float64)[None],
                      np.asarray(sides, dtype=np.float64)[None])[0]


def keep_at(record: Record, thresholds: Sequence[float], min_sides: Sequence[float] | None = None) -> Record:
    """The record with only the boxes ``kept_mask`` keeps; box ids are kept, so kept boxes still name the
    detections they came from."""
    keep = kept_mask(record, thresholds, min_sides)
    return replace(record, boxes=record.boxes[keep].copy(), relations=[], wheel_pairs=[])


class NoDetectorError(LookupError):
    """The bundle was exported without a detector (its run had ``pipeline.skip=[detector]``)."""


def bundle_operating_point(detector_cfg: dict) -> tuple[tuple[float, ...] | None, tuple[float, ...]]:
    """(per-class score thresholds, per-class minimum box sides) of a bundle's ``detector`` entry, in class order:
    the operating point chosen on val (deepword/operating_point/search.py). A bundle from before it existed has no
    thresholds (None: everything above ``score_threshold`` is kept) and no minimum sides."""
    names, floor = detector_cfg["class_names"], float(detector_cfg["score_threshold"])
    operating_point = detector_cfg.get("operating_point")
    if not operating_point:
        return None, (0.0,) * len(names)
    min_side = detector_cfg.get("min_side") or {}
    return (tuple(max(floor, float(operating_point[n])) for n in names),
            tuple(float(min_side.get(n, 0.0)) for n in names))


def bundle_footprint_point(detector_cfg: dict) -> tuple[float, ...] | None:
    """Per-class score thresholds (class order) of the detections the footprints are made from: the bundle's
    ``footprint_point`` ({class name: threshold}) where it is lower than the operating point's, the operating point's
    for the classes it leaves out; so the footprints see every detection the relations see, and more
    (docs/bev.md, "Which detections the footprints take"). None where the bundle has no operating point (everything
    above ``score_threshold`` is kept for both)."""
    thresholds, _ = bundle_operating_point(detector_cfg)
    if thresholds is None:
        return None
    names, floor = detector_cfg["class_names"], float(detector_cfg["score_threshold"])
    lower = detector_cfg.get("footprint_point") or {}
    return tuple(max(floor, min(t, float(lower[n]))) if lower.get(n) is not None else t
                 for n, t in zip(names, thresholds, strict=True))


class OnnxDetector:
    """The exported CenterNet: letterbox + normalise (``deepword.detection.letterbox``), onnxruntime, and the
    detector stage's own detections -> WORD record conversion."""

    def __init__(self, bundle_dir: str | os.PathLike, threads: int = 1, at_operating_point: bool = True):
        bundle_dir = Path(bundle_dir)
        cfg = read_bundle(bundle_dir)["detector"]
        if cfg is None:
            raise NoDetectorError(f"{bundle_dir}: this export has no detector (its pipeline run left it out with "
                                  "pipeline.skip=[detector]); use a run that trained one")
        self.input_width, self.input_height = int(cfg["input_width"]), int(cfg["input_height"])
        self.score_threshold = float(cfg["score_threshold"])
        # at_operating_point=False (AP, the search itself) keeps everything above score_threshold
        self.class_thresholds, self.class_min_sides = (
            bundle_operating_point(cfg) if at_operating_point else (None, (0.0,) * len(cfg["class_names"])))
        self.footprint_thresholds = bundle_footprint_point(cfg) if at_operating_point else None
        self.session = ort_session(bundle_dir / DETECTOR_FILE, threads)

    def detect(self, rgb: np.ndarray, source: Record) -> Record:
        """``source``'s image (RGB uint8) -> a record with its detected boxes (real scores, no relations), those
        under their class's operating-point threshold or minimum side left out."""
        return self.keep_operating_point(self.detect_every(rgb, source))

    def detect_every(self, rgb: np.ndarray, source: Record) -> Record:
        """``detect`` without the operating point: every detection down to ``score_threshold``."""
        x, box = preprocess(rgb, self.input_width, self.input_height)
        (detections,) = self.session.run(["detections"], {DETECTOR_INPUT: x[None]})
        return detections_to_record(detections[0], source, box, self.score_threshold)

    def keep_operating_point(self, record: Record) -> Record:
        """A ``detect_every`` record with the boxes under their class's operating-point threshold or minimum side
        left out (the record itself when this detector has no operating point)."""
        if self.class_thresholds is None:
            return record
        return renumbered(keep_at(record, self.class_thresholds, self.class_min_sides))

    def keep_footprint_point(self, record: Record) -> Record:
        """A ``detect_every`` record with the detections the footprints are made from (``bundle_footprint_point``,
        at the operating point's minimum sides): those ``keep_operating_point`` keeps, with the ids it gives them,
        and the ones only the footprint point keeps, numbered after them. So a footprint of one of these names the
        box of the operating point's record that it places, and the footprints' other boxes name none."""
        if self.footprint_thresholds is None or self.footprint_thresholds == self.class_thresholds:
            return self.keep_operating_point(record)
        relation = kept_mask(record, self.class_thresholds, self.class_min_sides)
        footprint = kept_mask(record, self.footprint_thresholds, self.class_min_sides) | relation
        ids = np.empty(len(record.boxes), dtype=np.int64)
        ids[relation] = np.arange(int(relation.sum()))
        ids[footprint & ~relation] = np.arange(int(relation.sum()), int(footprint.sum()))
        kept = replace(record, boxes=record.boxes[footprint].copy(), relations=[], wheel_pairs=[])
        return renumbered(kept, ids[footprint])
