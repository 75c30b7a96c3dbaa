"""Table 3-style rendering: rows = methods, columns = easy / hard / mixed, one table per metric."""

from __future__ import annotations

from deepword import paper
from deepword.metrics import METRICS
from deepword.scoring.pair_errors import FALSE_CAUSES, MISSED_CAUSES, RELATION_ORACLE
from deepword.word_format import SUBSETS

# The paper's Table 3 does not say whether per wheel or per image, so it is printed beside both.
PAPER_TABLE3 = {paper.TABLE3_LABELS[m]: tuple(acc[s] for s in SUBSETS) for m, acc in paper.TABLE3_ACCURACY.items()}
PAPER_METRICS = ("wheel_acc", "image_acc")
BOX_TITLES = {"gt": "ground-truth boxes", "detected": "detected boxes (end-to-end)"}
ORACLE_TITLE = "detected boxes, relations from the ground truth (the ceiling)"
ORACLE_NOTE = (f"`{RELATION_ORACLE}` is not a method: it is the ground truth's relations on the same boxes (matched "
               "at the evaluation's IoU), what a relation model that never errs would make of them "
               "(deepword/scoring/pair_errors.py). From a method's row up to it is what the relation model costs on "
               "these boxes; from it up to 100, what the boxes themselves cost (missed and misplaced boxes).")


def metric_name(boxes: str, method: str, subset: str, metric: str) -> str:
    """The MLflow key of docs/design.md §7."""
    return f"eval.{boxes}.{method}.{subset}.{metric}"


def flatten(results: dict) -> dict[str, float]:
    """{boxes: {method: {subset: {metric: value}}}} -> flat MLflow metrics."""
    return {metric_name(b, m, s, k): float(v)
            for b, methods in results.items() for m, subsets in methods.items()
            for s, metrics in subsets.items() for k, v in metrics.items() if k in METRICS}


def table3(methods: dict[str, dict[str, dict[str, float]]], metric: str, with_paper: bool) -> list[str]:
    lines = [f"| {metric} (%) | " + " | ".join(SUBSETS) + " |", "|---|" + "---:|" * len(SUBSETS)]
    for name, subsets in methods.items():
        lines.append(f"| {name} | " + " | ".join(f"{subsets[s][metric]:.2f}" if s in subsets else "-"
                                                  for s in SUBSETS) + " |")
    if with_paper:
        for name, row in PAPER_TABLE3.items():
            lines.append(f"| *{name}* | " + " | ".join(f"*{v:.2f}*" for v in row) + " |")
    return lines


HEADLINE_METHOD = "deepword"   # on ground-truth boxes, and on detected ones beside the bundle's end-to-end method
HEADLINE_METRICS = ("pair_f1", "pair_precision", "pair_recall", "image_acc")


def headline_metrics(results: dict, end_to_end: str = HEADLINE_METHOD) -> dict[str, float]:
    """The few numbers a run is judged by, first in the stage's metrics (the pipeline summary shows a stage's
    first ones): the end-to-end method's pair_f1 on detected boxes of hard and mixed images, DeepWORD's pair_f1 on
    ground-truth boxes of mixed ones to compare with, the end-to-end image_acc on hard, and DeepWORD alone end to
    end."""
    wanted = [("detected", end_to_end, "hard", "pair_f1"), ("detected", end_to_end, "mixed", "pair_f1"),
              ("gt", HEADLINE_METHOD, "mixed", "pair_f1"), ("detected", end_to_end, "hard", "image_acc"),
              ("detected", HEADLINE_METHOD, "hard", "pair_f1"), ("detected", HEADLINE_METHOD, "mixed", "pair_f1")]
    out = {}
    for boxes, method, subset, metric in wanted:
        if subset in results.get(boxes, {}).get(method, {}):
            out[metric_name(boxes, method, subset, metric)] = float(results[boxes][method][subset][metric])
    return out


def headline_markdown(results: dict, detector: dict | None, end_to_end: str = HEADLINE_METHOD) -> list[str]:
    """End to end first: the bundle's end-to-end method on detected boxes (and DeepWORD alone, when that is another
    method), the ceiling those boxes leave it (``relation_oracle``) and DeepWORD on ground-truth boxes, per subset,
    and the detector's AP and operating point (from the export bundle's ``detector`` entry) that the detected rows
    depend on."""
    detected, gt = results.get("detected", {}), results.get("gt", {})
    rows = [(BOX_TITLES["detected"], end_to_end, detected.get(end_to_end))]
    if end_to_end != HEADLINE_METHOD:
        rows.append((BOX_TITLES["detected"], HEADLINE_METHOD, detected.get(HEADLINE_METHOD)))
    if any(subsets is not None for *_, subsets in rows):  # the ceiling only means something beside a row it bounds
        rows.append((ORACLE_TITLE, "-", detected.get(RELATION_ORACLE)))
    rows.append((BOX_TITLES["gt"], HEADLINE_METHOD, gt.get(HEADLINE_METHOD)))
    rows = [row for row in rows if row[2] is not None]
    if not rows:
        return []
    out = [f"## End to end: `{end_to_end}` on detected boxes beside ground-truth boxes", "",
           "| boxes | method | " + " | ".join(f"{m} {s}" for m in HEADLINE_METRICS for s in SUBSETS) + " |",
           "|---|---|" + "---:|" * (len(HEADLINE_METRICS) * len(SUBSETS))]
    for title, method, subsets in rows:
        out.append(f"| {title} | {method} | " + " | ".join(
            f"{subsets[s][m]:.2f}" if s in subsets else "-" for m in HEADLINE_METRICS for s in SUBSETS) + " |")
    out.append("")
    if end_to_end != HEADLINE_METHOD:
        out += [f"`{end_to_end}` is the bundle's end-to-end method (`export.end_to_end`, what `deepword infer` runs "
                "on images): deepword/rules/fallback.py.", ""]
    if any(title == ORACLE_TITLE for title, *_ in rows):
        out += [ORACLE_NOTE, ""]
    if detector:
        ap = detector.get("ap") or {}
        classes = detector.get("class_names", [])
        if ap:
            out.append("Detector, test split: " + "; ".join(
                f"{c} AP@0.5 {ap.get(f'detector.test.ap50.{c}', float('nan')):.1f}, "
                f"AP@[.5:.95] {ap.get(f'detector.test.ap.{c}', float('nan')):.1f}" for c in classes) + ".")
        op = detector.get("operating_point")
        if op:
            sides = detector.get("min_side") or {}
            out.append(f"Operating point (chosen on val by the end-to-end pair_f1 of `{end_to_end}`): "
                       + ", ".join(f"{c} score >= {op[c]:.2f}" + (f" and >= {sides[c]:g} px" if sides.get(c) else "")
                                   for c in classes if c in op) + ".")
        out.append("")
    return out


def errors_markdown(errors: dict[str, dict[str, dict[str, int]]], boxes: str) -> list[str]:
    """{method: {subset: ``PairErrors.as_dict()``}} as a table: per method and subset, the true pairs found, the
    missed ones by cause and the false claims by cause (``deepword.scoring.pair_errors``)."""
    if not errors:
        return []
    causes = [("missed", k, label) for k, label in MISSED_CAUSES.items()] + \
             [("false", k, label) for k, label in FALSE_CAUSES.items()]
    out = [f"## Where the pair errors are: {BOX_TITLES.get(boxes, boxes)}", "",
           "Each missed true pair and each false claim put down to one cause (deepword/scoring/pair_errors.py): "
           "the missed ones add up to the pairs pair_recall misses, the false ones to those pair_precision counts "
           "against.", "",
           "| method | subset | true pairs found | " + " | ".join(f"{kind}: {label}" for kind, _, label in causes) + " |",
           "|---|---|---:|" + "---:|" * len(causes)]
    for method, subsets in errors.items():
        for subset in SUBSETS:
            if subset in subsets:
                row = subsets[subset]
                counts = " | ".join(str(row[k]) for _, k, _ in causes)
                out.append(f"| {method} | {subset} | {row['found']} | {counts} |")
    return out + [""]


def render_markdown(results: dict, sizes: dict[str, dict[str, int]], notes: list[str], title: str,
                    lead: list[str] | None = None, errors: dict | None = None) -> str:
    """``results`` as in ``flatten``; ``sizes[subset]`` = {"images": n, "wheels": n evaluated}; ``lead``:
    markdown lines shown before the per-metric tables (the end-to-end headline); ``errors``: {boxes: {method:
    {subset: pair errors by cause}}}, shown after each box source's tables."""
    out = [f"# {title}", ""]
    out.append("Subsets: " + ", ".join(f"{s} = {sizes[s]['images']} images / {sizes[s]['wheels']} evaluated wheels"
                                       for s in SUBSETS if s in sizes) + ".")
    out.append("Metrics in percent (docs/design.md §7). The paper's Table 3 rows (italic) are printed beside "
               "wheel_acc and image_acc because the paper does not say which one it reports.")
    out.append("")
    out += lead or []
    # detected boxes first: end to end is what a user with images gets
    for boxes, methods in sorted(results.items(), key=lambda item: item[0] != "detected"):
        out += [f"## {BOX_TITLES.get(boxes, boxes)}", ""]
        if RELATION_ORACLE in methods:
            out += [ORACLE_NOTE, ""]
        for metric in METRICS:
            out += table3(methods, metric, metric in PAPER_METRICS) + [""]
        out += errors_markdown((errors or {}).get(boxes, {}), boxes)
    if notes:
        out += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(out)
