"""Table 3-style rendering: rows = methods, columns = easy / hard / mixed, one table per metric."""

from __future__ import annotations

from stages import paper
from stages.metrics import METRICS
from stages.word_format import SUBSETS

# The paper's Table 3 does not say whether per wheel or per image, so it is printed beside both.
PAPER_TABLE3 = {paper.TABLE3_LABELS[m]: tuple(acc[s] for s in SUBSETS) for m, acc in paper.TABLE3_ACCURACY.items()}
PAPER_METRICS = ("wheel_acc", "image_acc")
BOX_TITLES = {"gt": "ground-truth boxes", "detected": "detected boxes (end-to-end)"}


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


def render_markdown(results: dict, sizes: dict[str, dict[str, int]], notes: list[str], title: str) -> str:
    """``results`` as in ``flatten``; ``sizes[subset]`` = {"images": n, "wheels": n evaluated}."""
    out = [f"# {title}", ""]
    out.append("Subsets: " + ", ".join(f"{s} = {sizes[s]['images']} images / {sizes[s]['wheels']} evaluated wheels"
                                       for s in SUBSETS if s in sizes) + ".")
    out.append("Metrics in percent (docs/design.md §7). The paper's Table 3 rows (italic) are printed beside "
               "wheel_acc and image_acc because the paper does not say which one it reports.")
    out.append("")
    for boxes, methods in results.items():
        out += [f"## {BOX_TITLES.get(boxes, boxes)}", ""]
        for metric in METRICS:
            out += table3(methods, metric, metric in PAPER_METRICS) + [""]
    if notes:
        out += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(out)
