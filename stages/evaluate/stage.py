"""The `evaluate` stage: every configured method on every available box source, scored on the
easy / hard / mixed test subsets; report.json, report.md, fitted baseline parameters, predictions and a
gallery of disagreements."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

from stages.evaluate.baselines import baseline_params
from stages.evaluate.gallery import write_gallery
from stages.evaluate.methods import BOX_SOURCES, METHODS, EvalContext
from stages.evaluate.report import PAPER_TABLE3, flatten, headline_markdown, headline_metrics, render_markdown
from stages.metrics import evaluated_wheel_ids, score_records
from stages.priors.mixture import load_priors
from stages.word_format import SUBSETS, open_dataset, write_records

BASELINES_FILE = "baselines.json"


def detector_entry(inputs: dict[str, Path]) -> dict | None:
    """The export bundle's detector entry (AP, operating point), or None without an export or a detector."""
    if "export" not in inputs:
        return None
    from stages.inference.runtime import read_bundle

    return read_bundle(inputs["export"]).get("detector")


def predictions_file(pred_dir: Path, boxes: str, method: str) -> Path:
    """Where a method's predictions on a box source are written (the bev stage reads them back)."""
    return Path(pred_dir) / f"{boxes}_{method}.jsonl"


def build_methods(ctx: EvalContext) -> dict[str, object]:
    """Instantiate (fit) the configured methods; a method whose inputs are absent is noted and skipped."""
    methods = {}
    for name in ctx.cfg.methods:
        if name not in METHODS:
            raise ValueError(f"eval.methods: unknown method {name!r}; known: {sorted(METHODS)}")
        method = METHODS[name](ctx)
        if method is None:
            ctx.notes.append(f"`{name}` skipped: an upstream stage it needs is not an input of evaluate")
        else:
            methods[name] = method
    return methods


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    ecfg, seed = cfg.eval, int(cfg.seed)
    ds = open_dataset(inputs["data"])
    ctx = EvalContext(cfg=ecfg, seed=seed, inputs=dict(inputs), dataset=ds, priors=load_priors(inputs["priors"]))
    methods = build_methods(ctx)
    min_px, iou = float(ecfg.min_box_px), float(ecfg.match_iou)
    subsets = {s: ds.subset(s) for s in SUBSETS}

    results: dict = {}
    gt_predictions: dict[str, dict] = {}
    pred_dir = out_dir / "predictions"
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
        results[boxes] = {}
        for name, method in methods.items():
            preds = {img: method.predict(rec) for img, rec in inputs_by_image.items()}
            write_records(predictions_file(pred_dir, boxes, name), list(preds.values()))
            results[boxes][name] = {s: score_records(recs, preds, min_px, iou).percentages()
                                    for s, recs in subsets.items()}
            if boxes == "gt":
                gt_predictions[name] = preds

    sizes = {s: {"images": len(recs), "wheels": sum(len(evaluated_wheel_ids(r, min_px)) for r in recs)}
             for s, recs in subsets.items()}
    report = {"results": results, "sizes": sizes, "notes": ctx.notes, "paper_table3": PAPER_TABLE3,
              "min_box_px": min_px, "match_iou": iou}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    lead = headline_markdown(results, detector_entry(inputs))
    (out_dir / "report.md").write_text(render_markdown(results, sizes, ctx.notes, "Table 3: owner-member relations",
                                                       lead))
    (out_dir / BASELINES_FILE).write_text(json.dumps(
        {name: baseline_params(m) for name, m in methods.items() if name in ("logic", "logic_plus", "prior")},
        indent=1))

    artifacts = out_dir / "artifacts"
    artifacts.mkdir(exist_ok=True)
    for name in ("report.md", "report.json", BASELINES_FILE):
        shutil.copy(out_dir / name, artifacts / name)
    test = ds.subset("test")
    write_gallery(artifacts / "gallery", ds.root, test, gt_predictions, int(ecfg.gallery_images), min_px)
    return {**headline_metrics(results), **flatten(results)}
