"""``deepword tune``: choose a bundle's detector operating point again, on labelled images of your own.

    deepword tune --dataset ROOT --out DIR [--split val] [--run RUN_ID | --export DIR]
                  [--prior DATA --prior-split val --prior-images 40]

The export stage chose the per-class score thresholds and minimum box sides on our synthetic val split
(``deepword.operating_point.search``). Other cameras, lenses and scenes score differently: a threshold that was
best there can keep too many boxes, or too few, on yours. With a few dozen labelled images (WORD format:
``labels.jsonl`` with relations, or a data stage output and ``--split``) this runs the bundle's detector on them,
searches the same grid by the same criterion (end-to-end pair_f1 of the bundle's end-to-end method, or
``--method``) and writes ``DIR``: a copy of the bundle whose ``export.json`` holds the new point (and ``tuned``:
where it came from and what it scored), with ``artifacts/operating_point.{md,png}`` of this search. Use it with
``deepword infer --export DIR``. Torch is never imported; each subset of an image's boxes runs the ONNX relation
model whole: a hundred images and the export stage's 6,760 points take 4-5 minutes on two threads.

On a few dozen images the best point is mostly noise. ``--prior`` adds labelled images of another domain scored by
the same bundle (e.g. the run's own val split: ``--prior <its data stage output> --prior-split val``), their counts
weighed as ``--prior-images`` of yours (``deepword.operating_point.search.Prior``): as your images outnumber that, they
decide.

Choose on images you will not report results on: a point chosen and scored on the same images flatters itself.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from deepword.inference.runtime import (
    BUNDLE_FILE,
    METHOD_VARIANTS,
    NoDetectorError,
    NoRuleError,
    OnnxDetector,
    OnnxRelation,
    bundle_operating_point,
    bundle_rule,
    end_to_end_method,
    read_bundle,
)
from deepword.operating_point.report import write_operating_point_report
from deepword.operating_point.search import (
    CRITERION,
    DEFAULT_GRID,
    OperatingPoint,
    Prior,
    SubsetRelation,
    end_to_end_score,
    search_operating_point,
)
from deepword.progress import ProgressCounter, progress_lines
from deepword.rules.fallback import FALLBACKS, batch_with_fallback
from deepword.scoring.score import ScoreError, load_ground_truth
from deepword.word_format import DatasetError, Record, boxes_only, load_image
from deepword.word_format.dataset import open_dataset
from stages.inference.image_cache import DEFAULT_BUDGET_MB, DecodedImages
from stages.inference.infer import resolve_dirs
from stages.inference.resolve import ResolveError

TUNED_METHODS = ("deepword", *FALLBACKS)
PRIOR_KEY = "prior:"   # the prior's records are keyed apart from the tuning images


class TuneError(RuntimeError):
    """A usage or input problem reported as one line (exit code 2)."""


def parse_values(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise TuneError(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if not values or min(values) < 0:
        raise TuneError(f"{what}: need one or more numbers >= 0, got {text!r}")
    return values


def search_space(bundle: dict, grid: str | None, min_sides: list[str]) -> tuple[list[float], dict[str, list[float]]]:
    """(score thresholds, {class: minimum sides}): the options, else what the export stage searched (recorded in
    the bundle), else every threshold of the default grid and no size limit."""

    classes = list(bundle["detector"]["class_names"])
    searched = bundle["detector"].get("operating_point_search") or {}
    thresholds = parse_values(grid, "--grid") if grid else list(searched.get("grid", DEFAULT_GRID))
    sides = {c: list(v) for c, v in (searched.get("min_side_grid") or {}).items()}
    for item in min_sides:
        name, _, values = item.partition("=")
        if name not in classes or not values:
            raise TuneError(f"--min-side: expected CLASS=PX[,PX...] with CLASS one of {classes}, got {item!r}")
        sides[name] = parse_values(values, f"--min-side {name}")
    return thresholds, {c: sides.get(c, [0.0]) for c in classes}


def tuning_records(dataset: Path, split: str | None) -> tuple[Path, list[Record]]:
    """The labelled images to tune on: a WORD-style dataset's records, or one split of a data stage output."""

    if split is None:
        try:
            return load_ground_truth(dataset)
        except ScoreError as exc:
            raise TuneError(str(exc)) from None

    if not (dataset / "splits.json").is_file():
        raise TuneError(f"--split {split}: {dataset} has no splits.json (only a data stage output has splits); "
                        "leave --split out to tune on every image of the dataset")
    ds = open_dataset(dataset)
    try:
        return ds.root, ds.subset(split)
    except KeyError as exc:
        raise TuneError(f"--split: {exc.args[0]}") from None


def tune(args) -> dict:
    """Run the search and write the tuned bundle; returns its ``tuned`` entry."""
    export = resolve_dirs(args, need_detector=True)["export"]
    bundle = read_bundle(export)
    if args.out.resolve() == Path(export).resolve():
        raise TuneError("--out must be a new folder, not the bundle itself")
    if args.out.exists() and not (args.out / BUNDLE_FILE).is_file():
        raise TuneError(f"{args.out}: exists and is not a bundle; choose a new folder")
    if not bundle.get("detector"):
        raise TuneError(f"{export / BUNDLE_FILE}: the bundle has no detector, so no operating point to tune")
    name = args.method or end_to_end_method(export)
    if name not in TUNED_METHODS:
        raise TuneError(f"--method {name}: tune chooses the point for one of {list(TUNED_METHODS)}")
    root, truths = tuning_records(args.dataset, args.split)
    if not truths:
        raise TuneError(f"{args.dataset}: no labelled images to tune on")
    classes = list(bundle["detector"]["class_names"])
    thresholds, sides = search_space(bundle, args.grid, args.min_side)
    # the export stage's evaluation protocol, else the evaluation's defaults
    searched = bundle["detector"].get("operating_point_search") or {}
    min_box_px = float(searched.get("min_box_px", 8.0)) if args.min_box_px is None else args.min_box_px
    match_iou = float(searched.get("match_iou", 0.5)) if args.match_iou is None else args.match_iou
    smoothing = int(searched.get("smoothing", 0)) if args.smoothing is None else args.smoothing
    if smoothing < 0:
        raise TuneError(f"--smoothing {smoothing}: expected a number of grid steps >= 0")

    prior_root, prior_truths = (None, []) if args.prior is None else tuning_records(args.prior, args.prior_split)
    if args.prior is not None and not prior_truths:
        raise TuneError(f"--prior {args.prior}: no labelled images")
    if args.prior_images < 0:
        raise TuneError(f"--prior-images {args.prior_images:g}: expected a weight >= 0 (in images)")
    # (dataset root, record as stored, record as searched): the prior's images keyed apart from yours, since two
    # datasets may well both hold images/front/000000.png
    keyed = [replace(t, image=f"{PRIOR_KEY}{t.image}") for t in prior_truths]
    sources = [(root, t, t) for t in truths] + [(prior_root, t, k) for t, k in zip(prior_truths, keyed, strict=True)]
    prior_truths = keyed

    detector = OnnxDetector(export, args.threads, at_operating_point=False)
    # the detector's pass and the relation network's read each image: kept decoded between them within the budget
    # (stages/inference/image_cache.py)
    pixels = DecodedImages(DEFAULT_BUDGET_MB * 2**20)
    stored_of = {truth.image: (source_root, stored) for source_root, stored, truth in sources}

    def rgb_of(rec: Record) -> np.ndarray:
        return pixels.get(rec.image, lambda: load_image(*stored_of[rec.image]))

    found = []
    # a bar on a terminal, plain lines in a log (deepword/progress.py)
    for _, _, truth in progress_lines(sources, len(sources), "detector", "image"):
        found.append(detector.detect_every(rgb_of(truth), boxes_only(truth)))
    detections, prior_detections = found[:len(truths)], found[len(truths):]
    progress = ProgressCounter("relation model on subsets of the boxes", "subset")
    relation = SubsetRelation(OnnxRelation(export, "dynamic", args.threads), found, rgb_of, progress=progress)
    pixels.clear()   # every image's graph (its boxes' crops) is built: the decoded images are not needed again
    method = relation if name in METHOD_VARIANTS else batch_with_fallback(relation, bundle_rule(export, FALLBACKS[name][1]))
    points = len(thresholds) ** len(classes) * math.prod(len(v) for v in sides.values())
    print(f"searching {points} operating points by the {CRITERION} of {name} ...", file=sys.stderr)
    prior = Prior(prior_truths, prior_detections, args.prior_images) if prior_truths else None
    chosen, seen = search_operating_point(truths, detections, method, len(classes), thresholds,
                                          [sides[c] for c in classes], min_box_px, match_iou, smoothing, prior)
    progress.close()
    shipped_thresholds, shipped_sides = bundle_operating_point(bundle["detector"])
    before = OperatingPoint(shipped_thresholds or (detector.score_threshold,) * len(classes), shipped_sides)
    floor = OperatingPoint((detector.score_threshold,) * len(classes), (0.0,) * len(classes))
    # either may lie off the searched grid
    f1_before, f1_floor = (seen[p] if p in seen and prior is None else
                           end_to_end_score(truths, detections, p, method, min_box_px, match_iou) for p in (before, floor))
    f1_chosen = seen[chosen] if prior is None else end_to_end_score(truths, detections, chosen, method, min_box_px,
                                                                    match_iou)

    if args.out.exists():
        shutil.rmtree(args.out)
    shutil.copytree(export, args.out)
    bundle["detector"]["operating_point"] = dict(zip(classes, chosen.thresholds, strict=True))
    bundle["detector"]["min_side"] = dict(zip(classes, chosen.min_sides, strict=True))
    tuned = {"dataset": str(args.dataset.resolve()), "split": args.split, "images": len(truths), "method": name,
             "from": str(Path(export).resolve()), CRITERION: f1_chosen, f"{CRITERION}_at_bundle_point": f1_before,
             "bundle_point": {"operating_point": dict(zip(classes, before.thresholds, strict=True)),
                              "min_side": dict(zip(classes, before.min_sides, strict=True))},
             "min_box_px": min_box_px, "match_iou": match_iou, "smoothing": smoothing, "points": len(seen)}
    if prior is not None:
        tuned["prior"] = {"dataset": str(args.prior.resolve()), "split": args.prior_split, "images": len(prior_truths),
                          "weighed_as_images": args.prior_images, f"{CRITERION}_with_prior": seen[chosen]}
    bundle["tuned"] = tuned
    (args.out / BUNDLE_FILE).write_text(json.dumps(bundle, indent=1))
    images = f"{len(truths)} labelled images" + (f" (split {args.split})" if args.split else "")
    if prior is not None:
        images += f", with {len(prior_truths)} prior images weighed as {args.prior_images:g}"
    # the report shows the search's values (pooled with a prior), its floor row too
    write_operating_point_report(args.out / "artifacts", seen, chosen, classes, seen.get(floor, f1_floor), name,
                                 images=images)
    return tuned


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="deepword tune", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", type=Path, required=True,
                   help="labelled images: a WORD-style dataset root (labels.jsonl) or a data stage output")
    p.add_argument("--split", help="with a data stage output: the split to tune on (e.g. val); default every image")
    p.add_argument("--out", type=Path, required=True, help="the tuned bundle's folder (a copy of the bundle)")
    p.add_argument("--method", choices=TUNED_METHODS, default=None,
                   help=f"the method whose end-to-end {CRITERION} chooses the point (default: the bundle's end-to-end method)")
    p.add_argument("--grid", help="score thresholds tried for every class, comma-separated (default: the export "
                   "stage's grid)")
    p.add_argument("--min-side", action="append", default=[], metavar="CLASS=PX,...",
                   help="minimum shorter box sides tried for a class (default: the export stage's; repeatable)")
    p.add_argument("--min-box-px", type=float, default=None,
                   help="evaluated wheels' minimum shorter side (default: the export stage's, else 8)")
    p.add_argument("--match-iou", type=float, default=None,
                   help="IoU for matching detections to labelled boxes (default: the export stage's, else 0.5)")
    p.add_argument("--smoothing", type=int, default=None,
                   help="choose the point whose neighbourhood of this many threshold grid steps scores best on "
                        "average, not the single best point: steadier on a few dozen images (default: the export "
                        "stage's)")
    p.add_argument("--prior", type=Path, help="labelled images of another domain (e.g. the run's data stage output "
                   "with --prior-split val) whose counts steady the choice on a few images of yours")
    p.add_argument("--prior-split", help="with a data stage output as --prior: its split (e.g. val)")
    p.add_argument("--prior-images", type=float, default=40.0,
                   help="the prior weighs as this many of your images (default 40)")
    p.add_argument("--run", help="MLflow run id of the pipeline run whose bundle to tune (default: newest)")
    p.add_argument("--export", type=Path, help="an export stage output directory (instead of --run)")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)")
    p.add_argument("--cache-dir", help="the pipeline's cache directory (default: $DEEPWORD_CACHE or the run's)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    args.evaluate = None   # resolve_dirs' baselines: not needed here

    try:
        tuned = tune(args)
    except (TuneError, DatasetError, ResolveError, NoDetectorError, NoRuleError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    point = json.loads((args.out / "export.json").read_text())["detector"]
    print(f"operating point on {tuned['images']} images: scores {point['operating_point']}, minimum sides "
          f"{point['min_side']}; {tuned['method']} {CRITERION} {tuned[CRITERION]:.2f} "
          f"(the bundle's point: {tuned[f'{CRITERION}_at_bundle_point']:.2f}) -> {args.out}")
    print(f"use it: deepword infer IMAGE... --export {args.out} --out PREDS", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
