"""The `evaluate` stage: every configured method on every available box source, scored on the
easy / hard / mixed test subsets; report.json, report.md, fitted baseline parameters, predictions and a
gallery of disagreements. With the held-out domain's dataset among its inputs (``shift_data``) it scores
every row there too, with the same fitted baselines and models: ``eval.shift.*``, ``detector.shift.*``,
``shift/report.md``."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

from deepword.detection.ap_errors import ap_error_breakdown, append_breakdown, error_metrics
from deepword.inference.runtime import end_to_end_method, read_bundle
from deepword.metrics import evaluated_wheel_ids, score_records
from deepword.priors import load_priors
from deepword.rules.baselines import BASELINES_FILE, baseline_params
from deepword.scoring.pair_errors import RELATION_ORACLE, pair_errors_records, relation_oracle
from deepword.scoring.report import (
    HEADLINE_METHOD,
    PAPER_TABLE3,
    flatten,
    headline_markdown,
    headline_metrics,
    render_markdown,
)
from deepword.word_format import CLASS_NAMES, SUBSETS, open_dataset, write_records
from stages.detector.stage import ap_metrics
from stages.evaluate.gallery import write_gallery
from stages.evaluate.methods import (
    BOX_SOURCES,
    FITTED_ON_TRAIN,
    METHODS,
    EvalContext,
    detections_for_ap,
    footprint_detections,
)

SHIFT_DIR = "shift"   # the held-out domain's predictions and report


def bundle_entries(inputs: dict[str, Path]) -> tuple[dict | None, str]:
    """The export bundle's detector entry (AP, operating point; None without an export or a detector) and its
    end-to-end method (``deepword`` without an export)."""
    if "export" not in inputs:
        return None, HEADLINE_METHOD

    return read_bundle(inputs["export"]).get("detector"), end_to_end_method(inputs["export"])


def predictions_file(pred_dir: Path, boxes: str, method: str) -> Path:
    """Where a method's predictions on a box source are written: the stage's declared output ``predictions``
    (conf/config.yaml: ``predictions/{boxes}_{method}.jsonl``, which the bev stage reads)."""
    return Path(pred_dir) / f"{boxes}_{method}.jsonl"


FOOTPRINT_BOXES = "footprints"   # the box name of the footprint point's predictions (conf/config.yaml, bev reads them)


def build_methods(ctx: EvalContext, fitted: dict[str, object] | None = None) -> dict[str, object]:
    """Instantiate (fit) the configured methods; a method whose inputs are absent is noted and skipped. Rows of
    ``FITTED_ON_TRAIN`` found in ``fitted`` (the same rows fitted on the same train sample) are reused as they are."""
    methods = {}
    for name in ctx.cfg.methods:
        if name not in METHODS:
            raise ValueError(f"eval.methods: unknown method {name!r}; known: {sorted(METHODS)}")
        reuse = fitted is not None and name in FITTED_ON_TRAIN and name in fitted
        method = fitted[name] if reuse else METHODS[name](ctx)
        if method is None:
            ctx.notes.append(f"`{name}` skipped: an upstream stage it needs is not an input of evaluate")
        else:
            methods[name] = method
    return methods


def score_dataset(ctx: EvalContext, methods: dict, pred_dir: Path) -> tuple[dict, dict, dict]:
    """Every method on every box source over ``ctx.dataset``'s test subsets: (results, pair errors by cause
    ({boxes: {method: {subset: counts}}}), predictions ({boxes: {method: {image: record}}})). Detected boxes also
    get the ``relation_oracle`` row: the ground truth's relations on them, the ceiling they leave the methods."""
    ecfg, ds = ctx.cfg, ctx.dataset
    min_px, iou = float(ecfg.min_box_px), float(ecfg.match_iou)
    subsets = {s: ds.subset(s) for s in SUBSETS}
    results: dict = {}
    errors: dict = {}
    predictions: dict[str, dict] = {}
    pred_dir.mkdir(parents=True, exist_ok=True)
    for boxes in ecfg.box_sources:
        if boxes not in BOX_SOURCES:
            raise ValueError(f"eval.box_sources: unknown source {boxes!r}; known: {sorted(BOX_SOURCES)}")
        inputs_by_image = BOX_SOURCES[boxes](ctx)
        if inputs_by_image is None:
            ctx.notes.append(f"`{boxes}` boxes skipped: this run has no detector (not an input of evaluate, "
                             "or left out with pipeline.skip)")
            continue
        for rec in ds.subset("test"):  # a test image without any box of this source: nothing detected
            inputs_by_image.setdefault(rec.image, replace(rec, boxes=rec.boxes[:0].copy(), relations=[],
                                                          wheel_pairs=[]))
        results[boxes], errors[boxes], predictions[boxes] = {}, {}, {}
        # every row on one image before the next: rows that read the image share its decoding (EvalContext.load_rgb)
        by_method: dict[str, dict] = {name: {} for name in methods}
        for img, rec in inputs_by_image.items():
            for name, method in methods.items():
                by_method[name][img] = method.predict(rec)
        for name, preds in by_method.items():
            write_records(predictions_file(pred_dir, boxes, name), list(preds.values()))
            results[boxes][name] = {s: score_records(recs, preds, min_px, iou).percentages()
                                    for s, recs in subsets.items()}
            errors[boxes][name] = {s: pair_errors_records(recs, preds, min_px, iou).as_dict()
                                   for s, recs in subsets.items()}
            predictions[boxes][name] = preds
        if boxes != "gt":  # on the ground truth's own boxes the oracle is the ground truth: 100 everywhere
            truth = {rec.image: rec for rec in ds.subset("test")}
            oracle = {img: relation_oracle(truth[img], rec, iou) for img, rec in inputs_by_image.items() if img in truth}
            results[boxes][RELATION_ORACLE] = {s: score_records(recs, oracle, min_px, iou).percentages()
                                               for s, recs in subsets.items()}
            errors[boxes][RELATION_ORACLE] = {s: pair_errors_records(recs, oracle, min_px, iou).as_dict()
                                              for s, recs in subsets.items()}
    if "detected" in predictions:
        write_footprint_predictions(ctx, methods, pred_dir)
    return results, errors, predictions


def write_footprint_predictions(ctx: EvalContext, methods: dict, pred_dir: Path) -> None:
    """Every method on the detections the bev stage's footprints are made from (``footprint_detections``: the
    bundle's footprint point, below the operating point), written but not scored: the relations' figures are those at
    the operating point (docs/bev.md, "Which detections the footprints take"). Nothing without an exported
    detector (detected boxes from the detector stage's predictions: the bev stage reads the scored ones)."""
    inputs_by_image = footprint_detections(ctx)
    if inputs_by_image is None:
        return
    for name, method in methods.items():
        write_records(predictions_file(pred_dir, FOOTPRINT_BOXES, name),
                      [method.predict(r) for r in inputs_by_image.values()])


def subset_sizes(ds, min_px: float) -> dict:
    return {s: {"images": len(recs), "wheels": sum(len(evaluated_wheel_ids(r, min_px)) for r in recs)}
            for s, recs in ((s, ds.subset(s)) for s in SUBSETS)}


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    ecfg, seed = cfg.eval, int(cfg.seed)
    ds = open_dataset(inputs["data"])
    priors = load_priors(inputs["priors"])
    ctx = EvalContext(cfg=ecfg, seed=seed, inputs=inputs, dataset=ds, priors=priors)
    methods = build_methods(ctx)
    min_px, iou = float(ecfg.min_box_px), float(ecfg.match_iou)
    results, errors, predictions = score_dataset(ctx, methods, out_dir / "predictions")
    sizes = subset_sizes(ds, min_px)
    detector, end_to_end = bundle_entries(inputs)
    report = {"results": results, "pair_errors": errors, "sizes": sizes, "notes": ctx.notes,
              "paper_table3": PAPER_TABLE3, "min_box_px": min_px, "match_iou": iou, "end_to_end": end_to_end}
    metrics = flatten(results)
    if "shift_data" in inputs:
        metrics |= score_heldout(ctx, open_dataset(inputs["shift_data"]), out_dir / SHIFT_DIR, methods)
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    lead = headline_markdown(results, detector, end_to_end)
    (out_dir / "report.md").write_text(render_markdown(results, sizes, ctx.notes, "Table 3: owner-member relations",
                                                       lead, errors))
    (out_dir / BASELINES_FILE).write_text(json.dumps(
        {name: baseline_params(m) for name, m in methods.items() if name in FITTED_ON_TRAIN},
        indent=1))

    artifacts = out_dir / "artifacts"
    artifacts.mkdir(exist_ok=True)
    for name in ("report.md", "report.json", BASELINES_FILE):
        shutil.copy(out_dir / name, artifacts / name)
    if "shift_data" in inputs:
        for name in ("report.md", "report.json"):
            shutil.copy(out_dir / SHIFT_DIR / name, artifacts / f"shift_{name}")
    test = ds.subset("test")
    # where the methods disagree, on ground-truth boxes and end to end (the detector's boxes, matched at match_iou)
    for boxes, folder in (("gt", "gallery"), ("detected", "gallery_detected")):
        if boxes in predictions:
            write_gallery(artifacts / folder, ds.root, test, predictions[boxes], int(ecfg.gallery_images), min_px,
                          iou)
    return {**headline_metrics(results, end_to_end), **metrics}


def score_heldout(ctx: EvalContext, heldout, out_dir: Path, fitted: dict[str, object]) -> dict[str, float]:
    """Every row on the held-out domain's test set, with the baselines the in-domain rows were fitted with
    (``fitted``, on the in-domain train split): ``eval.shift.<boxes>.<method>.<subset>.<metric>`` and, with
    detections, ``detector.shift.{ap50,ap}.<class>``; ``out_dir`` gets the predictions and report.md/json."""

    shift_ctx = EvalContext(cfg=ctx.cfg, seed=ctx.seed, inputs=ctx.inputs, dataset=heldout, priors=ctx.priors,
                            fit_dataset=ctx.dataset)
    shift_ctx.train = ctx.train  # the same fitting sample: the held-out set has no train split
    results, errors, _ = score_dataset(shift_ctx, build_methods(shift_ctx, fitted), out_dir / "predictions")
    min_px = float(ctx.cfg.min_box_px)
    sizes = subset_sizes(heldout, min_px)
    (out_dir / "report.json").write_text(json.dumps({"results": results, "pair_errors": errors, "sizes": sizes,
                                                     "notes": shift_ctx.notes}, indent=1))
    (out_dir / "report.md").write_text(render_markdown(results, sizes, shift_ctx.notes,
                                                       "Held-out domain: owner-member relations", errors=errors))
    metrics = {k.replace("eval.", "eval.shift.", 1): v for k, v in flatten(results).items()}
    detections = detections_for_ap(shift_ctx)  # every score: the detector stage's AP protocol
    if detections is not None:
        test = heldout.subset("test")
        metrics |= ap_metrics(detections, test, "shift", min_px)
        breakdown = ap_error_breakdown(test, detections, CLASS_NAMES, min_px)
        append_breakdown(out_dir / "report.md", breakdown, "held-out test split", min_px)
        metrics |= error_metrics(breakdown, "shift")
    return metrics
