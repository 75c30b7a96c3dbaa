"""The `export` stage: the trained relation network, detector and facing network to ONNX, checked, quantised and timed.

1. export: relation (static N = max_objects; dynamic N), detector (dynamic batch), facing network (dynamic batch;
   ``export_facing_checked``: checked against PyTorch on the test images' vehicle crops), ``onnx.checker``;
   the detector is an optional input: without it (``pipeline.skip=[detector]``) the bundle holds the
   relation network only, and every detector step below is left out; so is the facing network (no facing stage, or
   one that found no 3D truth to learn from: ``"facing": null``);
2. parity against PyTorch on the test split (relation: every test image, both variants; detector:
   ``export.parity.detector_images`` images); a miss of the tolerances fails the stage;
3. INT8: onnxruntime dynamic quantisation of the dynamic relation model (``export.int8.op_types``), and
   its wheel_acc change against FP32 on the easy/hard/mixed test subsets (annotated boxes);
4. latency (``stages.export.latency``, ``relation_latency``): the dynamic relation model on test images at
   their real object counts (batch 1, and batch 10 padded to the largest of the 10), PyTorch eager on
   the same inputs in the same process, the static model padded to max_objects, INT8, detector;
5. the end-to-end method (``export.end_to_end``): the paper's IoU rule fitted on train and stored in the bundle, so
   that ``deepword_then_logic`` runs from the bundle alone; the detector's operating point is chosen on val by the
   end-to-end method's pair_f1;
6. registry: ``deepword-relation`` and ``deepword-detector`` (inside a pipeline run only).

The output directory is the self-contained bundle ``deepword.inference.runtime`` documents; reports go to
``artifacts/`` (``latency.md``, ``parity.json``, and with a detector ``operating_point.{md,png}``: what the
operating-point search saw).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deepword.detection.letterbox import preprocess
from deepword.inference.facing_net import FACING_FILE, FACING_INPUT, FACING_OUTPUT, vehicle_crops
from deepword.inference.runtime import (
    BUNDLE_FILE,
    DETECTOR_FILE,
    DETECTOR_INPUT,
    PRIORS_FILE,
    RELATION_FILES,
    OnnxDetector,
    OnnxRelation,
    ort_session,
)
from deepword.metrics import score_records
from deepword.operating_point.report import write_operating_point_report
from deepword.operating_point.search import (
    CRITERION,
    OperatingPoint,
    Prior,
    SubsetRelation,
    end_to_end_score,
    search_operating_point,
)
from deepword.paper import DSP_LATENCY
from deepword.priors import load_priors
from deepword.relation_graph import InputConfig, build_graph
from deepword.rules.baselines import baseline_params, fit_couple_rule, fit_logic, prepare_train
from deepword.rules.fallback import FALLBACKS, batch_with_fallback
from deepword.word_format import CLASS_NAMES, PRIOR_SPLIT, SUBSETS, boxes_only, load_image, open_dataset
from pipeline.tracking import stage_run_info
from stages.export.latency import batches, cpu_ms, graph_batches, onnx_ms, torch_ms
from stages.export.parity import ParityReport, detector_parity, relation_parity
from stages.export.registry import register_models

if TYPE_CHECKING:
    from stages.export.parity import ParityReport



def _limit(records: list, limit) -> list:
    return records if limit is None else records[: int(limit)]


def size_mb(path: Path) -> float:
    return path.stat().st_size / 2**20


def export_relation_models(net, out_dir: Path, input_size: int, max_objects: int, int8_op_types: list[str]) -> None:
    """The relation model's three ONNX files in ``out_dir`` (``RELATION_FILES``): static shapes, dynamic shapes and
    the dynamic one quantised to INT8 (``quantize_int8``)."""
    from stages.export.onnx_export import export_relation

    export_relation(net, out_dir / RELATION_FILES["static"], input_size, max_objects, static=True)
    export_relation(net, out_dir / RELATION_FILES["dynamic"], input_size, max_objects, static=False)
    quantize_int8(out_dir / RELATION_FILES["dynamic"], out_dir / RELATION_FILES["int8"], int8_op_types)


def quantize_int8(src: Path, dst: Path, op_types: list[str]) -> Path:
    """Dynamic INT8 quantisation (weights int8 offline, activations per call). Only MatMul/Gemm by
    default: onnxruntime's ConvInteger kernels are several times slower than its float convolutions,
    while the fully connected layers hold most of the weights."""
    import logging

    from onnxruntime.quantization import QuantType, quantize_dynamic

    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the quantiser logs every tensor it skips on the root logger
    try:
        quantize_dynamic(str(src), str(dst), weight_type=QuantType.QInt8, op_types_to_quantize=list(op_types))
    finally:
        root.setLevel(level)
    return dst


def write_bundle(out_dir: Path, meta: dict, det_cfg: dict | None, extra: dict,
                 operating_point: dict | None = None, detector_ap: dict | None = None,
                 min_sides: dict | None = None, end_to_end: dict | None = None, search: dict | None = None,
                 facing: dict | None = None, footprint_point: dict | None = None) -> None:
    """``export.json``; ``"detector": null`` (and no detector file) when the run had no detector. The
    detector's ``operating_point`` ({class name: score threshold}) and ``min_side`` ({class name: shorter box
    side in image pixels}), chosen on val, are what inference keeps; ``score_threshold`` is the lower bound of
    what its decoding returns at all. ``footprint_point`` ({class name: score threshold}): the lower thresholds of the
    detections the footprints are made from (``deepword.inference.runtime.bundle_footprint_point``). ``ap``: the
    detector stage's val/test AP, so that reports on this bundle can show it beside the end-to-end rows.
    ``end_to_end``: the method for detected boxes and the rules fitted on train it may fall back on
    (``end_to_end_entry``). ``search``: the grid the operating point was chosen from (``operating_point_search``),
    which ``deepword tune`` searches again.
    ``facing``: the facing network's crop settings and val accuracy (``"facing": null`` and no facing.onnx without
    one: ``deepword.inference.facing_net.OnnxFacing``)."""
    detector = None if det_cfg is None else {k: det_cfg[k] for k in ("input_width", "input_height", "max_detections",
                                                                      "score_threshold", "class_names")}
    if detector is not None:
        detector["operating_point"] = operating_point
        detector["min_side"] = min_sides or {}
        detector["footprint_point"] = footprint_point or {}
        detector["ap"] = detector_ap or {}
        if search is not None:
            detector["operating_point_search"] = search
    files = {**RELATION_FILES, "priors": PRIORS_FILE, **({} if det_cfg is None else {"detector": DETECTOR_FILE}),
             **({} if facing is None else {"facing": FACING_FILE})}
    bundle = {"relation": {"inputs": meta["inputs"], "decode": meta["decode"], "has_roles": meta["has_roles"],
                           "model": meta["model"]},
              "detector": detector, "facing": facing, "end_to_end": end_to_end, "files": files, **extra}
    (out_dir / BUNDLE_FILE).write_text(json.dumps(bundle, indent=1))


def wheel_acc_by_subset(ds, preds: dict, min_box_px: float) -> dict[str, float]:
    return {s: score_records(ds.subset(s), preds, min_box_px).percentages()["wheel_acc"] for s in SUBSETS}


def int8_accuracy_change(ds, out_dir: Path, records: list, graphs: list, min_box_px: float) -> dict[str, float]:
    """wheel_acc (percent) of the FP32 and INT8 models on the test subsets and the change in points."""
    inputs = [boxes_only(r) for r in records]
    acc = {}
    for variant in ("dynamic", "int8"):
        relation = OnnxRelation(out_dir, variant)
        # one image per call, as on the device: dynamic quantisation scales activations per call, so
        # batching images (and their padding) together would change INT8 results
        preds = [relation.predict_graphs([rec], [g])[0] for rec, g in zip(inputs, graphs, strict=True)]
        acc[variant] = wheel_acc_by_subset(ds, {p.image: p for p in preds}, min_box_px)
    metrics = {}
    for s in SUBSETS:
        metrics[f"export.relation.fp32.{s}.wheel_acc"] = acc["dynamic"][s]
        metrics[f"export.relation.int8.{s}.wheel_acc"] = acc["int8"][s]
        metrics[f"export.relation.int8.{s}.wheel_acc_change"] = acc["int8"][s] - acc["dynamic"][s]
    return metrics


def relation_latency(net, out_dir: Path, graphs: list, size: int, max_objects: int, lat) -> dict[str, float]:
    """The latency figures: the dynamic model on test images at their real object counts, batch 1 (one
    image per call) and batch 10 (10 consecutive images padded to the largest of them), with
    ``lat.threads`` threads; PyTorch eager on the same feeds; the one-thread CPU time (the cost without
    the machine's other load). ``static_*``: the static model, every image padded to max_objects, as an
    embedded runtime with static shapes runs it. INT8: the dynamic INT8 model at batch 1."""
    # imported here: it loads torch, which importing this module must not
    from stages.export.onnx_export import RelationGraph

    threads, runs, warmup = int(lat.threads), int(lat.runs), int(lat.warmup)
    feeds = {"b1": graph_batches(graphs, size, 1), "b10": graph_batches(graphs, size, 10)}
    padded = {"b1": graph_batches(graphs, size, 1, max_objects), "b10": graph_batches(graphs, size, 10, max_objects)}
    names = {"b1": "ms_per_img_b1", "b10": "ms_per_10img_b10"}
    sessions = {v: ort_session(out_dir / RELATION_FILES[v], threads) for v in ("dynamic", "static", "int8")}
    one_thread = {v: ort_session(out_dir / RELATION_FILES[v], 1) for v in ("dynamic", "static")}
    eager = RelationGraph(net).eval()
    m = {}
    for b, name in names.items():
        m[name] = onnx_ms(sessions["dynamic"], feeds[b], runs, warmup)
        m[f"torch_{name}"] = torch_ms(eager, feeds[b], runs, warmup, threads)
        m[f"cpu_{name}"] = cpu_ms(one_thread["dynamic"], feeds[b], runs, warmup)
        m[f"static_{name}"] = onnx_ms(sessions["static"], padded[b], runs, warmup)
        m[f"static_cpu_{name}"] = cpu_ms(one_thread["static"], padded[b], runs, warmup)
    m["speedup_vs_torch"] = m["torch_ms_per_img_b1"] / m["ms_per_img_b1"]
    m["speedup_vs_torch_b10"] = m["torch_ms_per_10img_b10"] / m["ms_per_10img_b10"]
    m["int8_ms_per_img_b1"] = onnx_ms(sessions["int8"], feeds["b1"], runs, warmup)
    m["objects_per_img"] = float(np.mean([len(g.classes) for g in graphs]))
    return {**{f"export.relation.{k}": float(v) for k, v in m.items()},
            "export.threads": float(threads), "export.latency_runs": float(runs)}


def detector_latency(det_net, out_dir: Path, images: np.ndarray, lat) -> dict[str, float]:
    threads, runs, warmup = int(lat.threads), int(lat.runs), int(lat.warmup)
    feeds = [{DETECTOR_INPUT: images[i:i + 1]} for i in range(len(images))]
    session = ort_session(out_dir / DETECTOR_FILE, threads)
    return {"export.detector.ms_per_img_b1": onnx_ms(session, feeds, runs, warmup),
            "export.detector.ms_per_10img_b10": onnx_ms(session, batches(feeds, 10), runs, warmup),
            "export.detector.torch_ms_per_img_b1": torch_ms(det_net, feeds, runs, warmup, threads)}


def latency_table(m: dict[str, float]) -> str:
    """Markdown: onnxruntime, PyTorch and the paper's embedded figures side by side."""
    threads = int(m["export.threads"])
    r = {k.removeprefix("export.relation."): v for k, v in m.items() if k.startswith("export.relation.")}

    def row(what: str, prefix: str, extra: str = "| | |") -> str:
        return f"| {what} | {r[prefix + 'ms_per_img_b1']:.2f} | {r[prefix + 'ms_per_10img_b10']:.1f} {extra}"

    rows = [
        f"Test images, {r['objects_per_img']:.1f} objects per image on average; batch 10 = 10 consecutive images.",
        "",
        "| model | ms/img (batch 1) | ms/10 imgs (batch 10) | params | size MB |",
        "|---|---|---|---|---|",
        row(f"relation, onnxruntime, threads={threads}, real object counts (batch 10: padded to its largest)", "",
            extra=f"| {r['params']:.0f} | {r['size_mb']:.2f} |"),
        row(f"relation, PyTorch eager, threads={threads}, same inputs", "torch_"),
        row("relation, onnxruntime, 1 thread, CPU time, real object counts", "cpu_"),
        row(f"relation, onnxruntime, threads={threads}, static model padded to max_objects", "static_"),
        row("relation, onnxruntime, 1 thread, CPU time, static model padded", "static_cpu_"),
        f"| relation INT8, onnxruntime, real object counts | {r['int8_ms_per_img_b1']:.2f} | | "
        f"| {r['int8.size_mb']:.2f} |",
        f"| paper (embedded DSP) | {DSP_LATENCY['ms_per_img_b1']} | {DSP_LATENCY['ms_per_10img_b10']} | | |",
    ]
    if "export.detector.ms_per_img_b1" in m:
        rows += [
            f"| detector, onnxruntime | {m['export.detector.ms_per_img_b1']:.2f} "
            f"| {m['export.detector.ms_per_10img_b10']:.1f} | {m['export.detector.params']:.0f} "
            f"| {m['export.detector.size_mb']:.2f} |",
            f"| detector, PyTorch eager | {m['export.detector.torch_ms_per_img_b1']:.2f} | | | |",
        ]
    return "\n".join(rows) + (f"\n\nonnxruntime is {r['speedup_vs_torch']:.2f}x faster than PyTorch eager at batch 1 "
                              f"and {r['speedup_vs_torch_b10']:.2f}x at batch 10 (same process, same inputs).\n")


def export_detector_checked(det_net, det_cfg: dict, ds, test: list, out_dir: Path, ex, tol: float,
                            agree: float) -> tuple[ParityReport, dict[str, float]]:
    """detector.onnx: exported, checked against PyTorch (a miss fails the stage) and timed; returns its
    parity report and its ``export.detector.*`` metrics."""
    # imported here: it loads torch, which importing this module must not
    from stages.export.onnx_export import export_detector

    export_detector(det_net, out_dir / DETECTOR_FILE, det_cfg["input_width"], det_cfg["input_height"],
                    det_cfg["max_detections"])
    images = np.stack([preprocess(load_image(ds.root, r), det_cfg["input_width"], det_cfg["input_height"])[0]
                       for r in _limit(test, ex.parity.detector_images)])
    report = detector_parity(det_net, ort_session(out_dir / DETECTOR_FILE, int(ex.latency.threads)), images,
                             det_cfg["max_detections"], det_cfg["score_threshold"])
    report.check("export: detector model", tol, agree)
    metrics = {**report.metrics("export.detector"),
               "export.detector.params": float(sum(p.numel() for p in det_net.parameters())),
               "export.detector.size_mb": size_mb(out_dir / DETECTOR_FILE),
               **detector_latency(det_net, out_dir, images[: int(ex.latency.images)], ex.latency)}
    return report, metrics


def export_facing_checked(net, meta: dict, crops: np.ndarray, out_dir: Path, ex) -> tuple[dict, dict]:
    """facing.onnx of the trained facing network ``net`` (``stages.facing.stage.load_network``), checked against
    PyTorch on ``crops`` (the test images' vehicle crops; a miss fails the stage, ``ParityReport.check``: a decision is
    the direction a vector points, agreeing where the two point the same way): the bundle's ``facing`` entry and the
    ``export.facing.*`` metrics."""
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.export.onnx_export import export_facing

    export_facing(net, out_dir / FACING_FILE, int(meta["input_size"]))
    report = ParityReport()
    if len(crops):
        with torch.no_grad():
            ref = net(torch.from_numpy(crops)).numpy()
        got = ort_session(out_dir / FACING_FILE, int(ex.latency.threads)).run([FACING_OUTPUT], {FACING_INPUT: crops})[0]
        same_way = ((ref * got).sum(1) > 0) | (np.linalg.norm(ref, axis=1) < 1e-6)
        report.add(float(np.abs(ref - got).max()), int(same_way.sum()), len(crops))
    report.check("export: facing model", float(ex.parity.max_abs_diff), float(ex.parity.min_agreement))
    entry = {"input_size": int(meta["input_size"]), "margin": float(meta["margin"]), "val_acc": float(meta["val_acc"]),
             "logit_scale": float(meta["logit_scale"])}
    return entry, {**report.metrics("export.facing"), "export.facing.parity_vehicles": float(len(crops)),
                   "export.facing.params": float(sum(p.numel() for p in net.parameters())),
                   "export.facing.size_mb": size_mb(out_dir / FACING_FILE), "export.facing.val_acc": entry["val_acc"]}


def end_to_end_entry(ds, e2e_cfg, min_box_px: float, seed: int) -> tuple[dict, object | None]:
    """``export.json``'s ``end_to_end`` entry ({"method": name, "rules": {rule: fitted parameters}}) and the method's
    fallback rule (None for ``deepword``). The paper's IoU rule is fitted on the train split exactly as the evaluate
    stage fits its ``logic`` row (the same seeded sample and grids: ``export.end_to_end.fit`` follows ``eval``), so
    the bundle's ``deepword_then_logic`` is the evaluate stage's row and ``deepword infer`` needs no baselines."""
    method = str(e2e_cfg.method)
    known = ["deepword", *FALLBACKS]
    if method not in known:
        raise ValueError(f"export.end_to_end.method: {method!r} is not one of {known}")
    train = prepare_train(ds.subset("train"), min_box_px, int(e2e_cfg.fit.images), seed)
    if not train:
        raise ValueError("export: the train split is empty; the end-to-end method's IoU rule is fitted on it")
    fit = e2e_cfg.fit
    rules = {"logic": fit_logic(train, fit_couple_rule(train, list(fit.couple_tolerance)), list(fit.logic_iou))}
    fallback = rules[FALLBACKS[method][1]] if method in FALLBACKS else None
    return {"method": method, "rules": {name: baseline_params(rule) for name, rule in rules.items()}}, fallback


def detector_ap(detector_dir: Path) -> dict[str, float]:
    """The detector stage's ``detector.{val,test}.{ap50,ap}.<class>`` metrics (its metrics.json)."""
    path = Path(detector_dir) / "metrics.json"
    metrics = json.loads(path.read_text()) if path.is_file() else {}
    return {k: float(v) for k, v in metrics.items() if k.startswith(("detector.val.", "detector.test."))}


def choose_operating_point(ds, out_dir: Path, det_cfg: dict, op_cfg, min_box_px: float, net=None,
                           tolerance: float = 1e-4, fallback=None, method_name: str = "") -> tuple[dict, dict, dict]:
    """Per-class score thresholds and minimum box sides of the exported detector, chosen on the val split by the
    end-to-end ``CRITERION`` (pair_f1) of the exported DeepWORD model, with ``fallback``'s claims for the wheels it leaves unclaimed
    when given (the bundle's end-to-end method; ``deepword.operating_point.search``); returns ({class: threshold},
    {class: minimum side in pixels}, metrics). With ``net``, the torch network the bundle's
    relation model was exported from, each box is embedded once (``stages.export.embedded_boxes``), after a
    check that this gives the bundle's scores on every val image's whole graph within ``tolerance``. Writes what
    the search saw to ``artifacts/operating_point.{md,png}`` (``deepword.operating_point.report``)."""
    val = _limit(ds.subset("val"), op_cfg.images)
    if not val:
        raise ValueError("export: the val split is empty; the detector's operating point is chosen on it")
    # a composed dataset's val_prior split (the generator's val beside a new camera's few val images) steadies the
    # choice, weighed as prior_images val images (deepword.operating_point.search.Prior)
    prior_weight = float(op_cfg.get("prior_images") or 0.0)
    if prior_weight < 0:
        raise ValueError(f"export.operating_point.prior_images: expected >= 0 images, got {prior_weight:g}")
    prior_truths = ds.subset(PRIOR_SPLIT) if prior_weight > 0 and PRIOR_SPLIT in ds.splits else []
    classes = list(det_cfg["class_names"])
    side_cfg = op_cfg.get("min_side_grid") or {}
    unknown = sorted(set(side_cfg) - set(classes))
    if unknown:
        raise ValueError(f"export.operating_point.min_side_grid: unknown classes {unknown}; the detector has {classes}")
    side_grid = [list(side_cfg.get(c, [0.0])) for c in classes]
    detector = OnnxDetector(out_dir, threads=int(op_cfg.threads), at_operating_point=False)
    images = {r.image: load_image(ds.root, r) for r in [*val, *prior_truths]}
    detections = [detector.detect(images[r.image], r) for r in val]
    prior_detections = [detector.detect(images[r.image], r) for r in prior_truths]
    shipped = OnnxRelation(out_dir, "dynamic", int(op_cfg.threads))
    embed = None
    if net is not None:
        from stages.export.embedded_boxes import EmbeddedBoxes  # torch: loaded only when a network is given

        def embed(graphs):
            return EmbeddedBoxes(net, graphs, shipped.flip_average)
    relation = SubsetRelation(shipped, [*detections, *prior_detections], lambda rec: images[rec.image], embed=embed)
    split_metrics = {}
    if relation.embedded is not None:
        diff = relation.embedded.max_abs_diff_to(shipped.scores)
        if diff > tolerance:
            raise RuntimeError(f"export: the relation model embedded once per box differs from {RELATION_FILES['dynamic']} "
                               f"by {diff:.2e} on the val graphs (tolerance {tolerance:.0e}); the operating-point "
                               "search would not score the shipped model")
        split_metrics["export.detector.operating_point_parity_max_abs_diff"] = diff
    match_iou = float(op_cfg.match_iou)
    method = relation if fallback is None else batch_with_fallback(relation, fallback)
    prior = Prior(prior_truths, prior_detections, prior_weight) if prior_truths else None
    chosen, seen = search_operating_point(val, detections, method, len(classes), list(op_cfg.grid), side_grid,
                                          min_box_px, match_iou, int(op_cfg.get("smoothing", 0)), prior)
    floor = OperatingPoint(tuple([float(det_cfg["score_threshold"])] * len(classes)), tuple([0.0] * len(classes)))

    def on_val(point: OperatingPoint) -> float:   # the val split's own figure (the search's pools in a prior)
        if prior is None and point in seen:
            return float(seen[point])
        return float(end_to_end_score(val, detections, point, method, min_box_px, match_iou))

    f1_floor = on_val(floor)
    # DeepWORD alone at the same point: what the fallback adds on val
    alone = float(end_to_end_score(val, detections, chosen, relation, min_box_px, match_iou))
    split_metrics[f"export.detector.val_{CRITERION}_deepword"] = alone
    searched_on = "the val split"
    if prior is not None:
        # the search's values pool both sets; the val split's own figure at the chosen point is reported beside
        split_metrics[f"export.detector.val_{CRITERION}_with_prior"] = float(seen[chosen])
        split_metrics["export.detector.prior_images"] = prior_weight
        split_metrics["export.detector.prior_split_images"] = float(len(prior_truths))
        searched_on = (f"the val split ({len(val)} images) with the {PRIOR_SPLIT} split ({len(prior_truths)} images) "
                       f"weighed as {prior_weight:g} images")
    # the report's values are the search's (pooled with a prior); DeepWORD alone is the val split's: left out there
    write_operating_point_report(out_dir / "artifacts", seen, chosen, classes, seen.get(floor, f1_floor), method_name,
                                 alone if fallback is not None and prior is None else None, images=searched_on)
    thresholds = dict(zip(classes, chosen.thresholds, strict=True))
    min_sides = dict(zip(classes, chosen.min_sides, strict=True))
    metrics = {**{f"export.detector.threshold.{c}": float(t) for c, t in thresholds.items()},
               **{f"export.detector.min_side.{c}": float(m) for c, m in min_sides.items()},
               f"export.detector.val_{CRITERION}": on_val(chosen),
               f"export.detector.val_{CRITERION}_at_score_threshold": float(f1_floor),
               "export.detector.operating_point_evaluations": float(len(seen)),
               "export.detector.operating_point_relation_runs": float(len(relation.predicted)), **split_metrics}
    return thresholds, min_sides, metrics


def footprint_thresholds(ex) -> dict[str, float]:
    """``export.footprint_point`` checked: {class name: score threshold in [0, 1]} (a null threshold: the operating
    point's, left out)."""
    out = {}
    for name, value in (ex.get("footprint_point") or {}).items():
        if name not in CLASS_NAMES:
            raise ValueError(f"export.footprint_point: unknown class {name!r}; known: {', '.join(CLASS_NAMES)}")
        if value is None:
            continue
        if not 0.0 <= float(value) <= 1.0:
            raise ValueError(f"export.footprint_point.{name}: {value} is not a score in [0, 1]")
        out[name] = float(value)
    return out


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.detector.model import load_detector
    from stages.export.onnx_export import folds_first_conv
    from stages.facing.stage import load_network as load_facing
    from stages.relation.model import count_parameters
    from stages.relation.stage import load_network

    ex, out_dir = cfg.export, Path(out_dir)
    footprint_point = footprint_thresholds(ex)
    torch.manual_seed(int(cfg.seed))
    ds = open_dataset(inputs["data"])
    net, meta = load_network(inputs["relation"])
    det_net, det_cfg = load_detector(inputs["detector"]) if "detector" in inputs else (None, None)
    in_cfg = InputConfig(**meta["inputs"])
    end_to_end, fallback = end_to_end_entry(ds, ex.end_to_end, float(ex.min_box_px), int(cfg.seed))
    shutil.copy(Path(inputs["priors"]) / PRIORS_FILE, out_dir / PRIORS_FILE)
    priors = load_priors(out_dir / PRIORS_FILE)

    export_relation_models(net, out_dir, in_cfg.input_size, in_cfg.max_objects, list(ex.int8.op_types))
    test = _limit(ds.subset("test"), ex.parity.images)
    if not test:
        raise ValueError("export: the test split is empty; parity and latency need test images")
    # the facing network (None: none trained, or no facing stage in the run), checked on the same test images' vehicles
    facing_net, facing_meta = load_facing(inputs["facing"]) if "facing" in inputs else (None, None)
    graphs, facing_crops = [], []
    for r in test:   # each test image decoded once: its relation graph and its vehicles' crops
        rgb = load_image(ds.root, r)
        graphs.append(build_graph(r, rgb, in_cfg, priors.wheel_vehicle, priors.wheel_wheel))
        if facing_net is not None:
            facing_crops.append(vehicle_crops(rgb, r, int(facing_meta["input_size"]), float(facing_meta["margin"]))[1])
    facing, facing_metrics = None, {}
    if facing_net is not None:
        facing, facing_metrics = export_facing_checked(facing_net, facing_meta, np.concatenate(facing_crops), out_dir,
                                                       ex)
    write_bundle(out_dir, meta, det_cfg, {}, end_to_end=end_to_end, facing=facing)

    threads, threshold = int(ex.latency.threads), float(meta["decode"]["threshold"])
    tol, agree = float(ex.parity.max_abs_diff), float(ex.parity.min_agreement)
    reports = {
        "static": relation_parity(net, ort_session(out_dir / RELATION_FILES["static"], threads), graphs,
                                  in_cfg.input_size, threshold, in_cfg.max_objects),
        "dynamic": relation_parity(net, ort_session(out_dir / RELATION_FILES["dynamic"], threads), graphs,
                                   in_cfg.input_size, threshold, None),
        "int8": relation_parity(net, ort_session(out_dir / RELATION_FILES["int8"], threads), graphs,
                                in_cfg.input_size, threshold, None),
    }
    for name in ("static", "dynamic"):
        reports[name].check(f"export: {name} model", tol, agree)
    det_metrics, operating_point, min_sides, det_ap, search = {}, None, None, None, None
    if det_net is not None:
        reports["detector"], det_metrics = export_detector_checked(det_net, det_cfg, ds, test, out_dir, ex, tol, agree)
        operating_point, min_sides, op_metrics = choose_operating_point(ds, out_dir, det_cfg, ex.operating_point,
                                                                        float(ex.min_box_px), net, tol, fallback,
                                                                        end_to_end["method"])
        det_metrics.update(op_metrics)
        det_ap = detector_ap(inputs["detector"])
        search = {"grid": [float(t) for t in ex.operating_point.grid],
                  "min_side_grid": {c: [float(v) for v in g]
                                    for c, g in (ex.operating_point.get("min_side_grid") or {}).items()},
                  "min_box_px": float(ex.min_box_px), "match_iou": float(ex.operating_point.match_iou),
                  "smoothing": int(ex.operating_point.get("smoothing", 0)),
                  "prior_images": float(det_metrics.get("export.detector.prior_images", 0.0)),
                  "prior_split_images": int(det_metrics.get("export.detector.prior_split_images", 0))}
        write_bundle(out_dir, meta, det_cfg, {}, operating_point, det_ap, min_sides, end_to_end, search, facing,
                     footprint_point)

    metrics = {
        "export.relation.parity_max_abs_diff": max(reports[v].max_abs_diff for v in ("static", "dynamic")),
        "export.relation.parity_decision_agreement": min(reports[v].decision_agreement for v in ("static", "dynamic")),
        "export.relation.parity_pairs": float(reports["static"].decisions),
        **reports["static"].metrics("export.relation.static"), **reports["dynamic"].metrics("export.relation.dynamic"),
        **reports["int8"].metrics("export.relation.int8"),
        "export.relation.params": float(count_parameters(net)),
        # 0: the backbone declares no first convolution, so the export could not fold the input normalisation
        # into it (logged as a warning; stages.export.onnx_export.FoldedBackbone)
        "export.relation.folded_first_conv": float(folds_first_conv(net)),
        "export.relation.size_mb": size_mb(out_dir / RELATION_FILES["static"]),
        "export.relation.int8.size_mb": size_mb(out_dir / RELATION_FILES["int8"]),
        **det_metrics, **facing_metrics,
    }
    metrics.update(int8_accuracy_change(ds, out_dir, test, graphs, float(ex.min_box_px)))
    lat_graphs = graphs[: int(ex.latency.images)]
    metrics.update(relation_latency(net, out_dir, lat_graphs, in_cfg.input_size, in_cfg.max_objects, ex.latency))

    artifacts = out_dir / "artifacts"
    artifacts.mkdir(exist_ok=True)
    (artifacts / "latency.md").write_text("# Latency (export stage)\n\n" + latency_table(metrics))
    (artifacts / "parity.json").write_text(json.dumps(
        {name: {"max_abs_diff": r.max_abs_diff, "decision_agreement": r.decision_agreement, "decisions": r.decisions}
         for name, r in reports.items()}, indent=1))
    registered = {}
    tracking = stage_run_info()
    if tracking is not None and bool(ex.register):

        models = {"relation": out_dir / RELATION_FILES["static"]}
        if det_net is not None:
            models["detector"] = out_dir / DETECTOR_FILE
        per_model = {m: {k: v for k, v in metrics.items() if k.startswith(f"export.{m}.")} for m in models}
        per_model["relation"].update({k: float(v) for k, v in meta.get("metrics", {}).items()})
        registered = register_models(tracking, models, per_model)
    write_bundle(out_dir, meta, det_cfg, {"metrics": metrics, "registered": registered, "threads": threads},
                 operating_point, det_ap, min_sides, end_to_end, search, facing, footprint_point)
    return metrics
