"""The default run in full, for docs/results.md: every relation method on both box sources, in domain and on the
held-out domain, with the ceiling of the detected boxes (the ground truth's relations on them), and the detector's
test AP. The same run as the headline (``stages.tables.headline.headline_run``), so that the page's figures agree
with the README's; ``make compare`` writes both."""

from __future__ import annotations

from deepword.scoring.report import metric_name
from deepword.word_format import SUBSETS
from pipeline.runs import RunRecord
from pipeline.tables import Table
from stages.tables.adapt import end_to_end_method
from stages.tables.headline import headline_run

DOMAINS = {"": "in domain", "shift.": "held out"}
# (boxes, method, label) in the order a reader compares them: the shipped method, its parts, the rules, the ceiling
RELATION_ROWS = (("detected", None, "`{e2e}` (what ships)"), ("detected", "deepword", "DeepWORD alone"),
                 ("detected", "logic", "`logic` (the paper's IoU rule)"), ("detected", "logic_plus", "`logic_plus`"),
                 ("detected", "relation_oracle", "*the ground truth's relations on these boxes (the ceiling)*"),
                 ("gt", "deepword", "DeepWORD"), ("gt", "logic", "`logic` (the paper's IoU rule)"),
                 ("gt", "logic_plus", "`logic_plus`"))
BOXES = {"detected": "detected", "gt": "ground truth"}
METRICS = ("pair_f1", "image_acc")
DETECTOR = (("ap50", "vehicle", "AP@0.5 vehicles"), ("ap50", "wheel", "AP@0.5 wheels"),
            ("ap", "vehicle", "AP@[.5:.95] vehicles"), ("ap", "wheel", "AP@[.5:.95] wheels"))
DETECTOR_DOMAINS = {"test": "in domain", "shift": "held out"}


def default_run_tables(runs: list[RunRecord]) -> tuple[list[Table], dict]:
    """The relation table and the detector table of the headline's run (``runs``: newest first)."""
    run = headline_run(runs)
    header = ["Domain", "Boxes", "Method", *(f"{m} {s}" for m in METRICS for s in SUBSETS)]
    detector_header = ["Domain", *(label for _, _, label in DETECTOR)]
    if run is None:
        note = ["No finished default run with end-to-end rows yet: run `make pipeline`, then `make compare`."]
        return [Table("The default run: every relation method", header, [], note),
                Table("The default run: the detector", detector_header, [], note)], {"default_run": None}
    m, e2e = run.metrics, end_to_end_method(run)
    rows = []
    for domain, domain_label in DOMAINS.items():
        for boxes, method, label in RELATION_ROWS:
            method = method or e2e
            cells = [m.get(metric_name(domain + boxes, method, s, k)) for k in METRICS for s in SUBSETS]
            if any(c is not None for c in cells):
                rows.append([domain_label, BOXES[boxes], label.format(e2e=e2e), *cells])
    provenance = (f"Run {run.name} ({run.tags.get('git_commit', '?')[:7]}), id {run.run_id}, profile "
                  f"{run.tags.get('profile', '?')}, seed {run.tags.get('seed', '?')}: the headline's run.")
    relations = Table("The default run: every relation method", header, rows, [
        "End to end: the detector's boxes at the operating point the export stage chose on val; ground truth: the "
        "labelled boxes. pair_f1 and image_acc as docs/design.md §7 defines them; the held-out domain is the generator's "
        "(docs/domain.md), never trained on.", provenance])
    detector_rows = []
    for split, label in DETECTOR_DOMAINS.items():
        cells = [m.get(f"detector.{split}.{kind}.{cls}") for kind, cls, _ in DETECTOR]
        if any(c is not None for c in cells):
            detector_rows.append([label, *cells])
    detector = Table("The default run: the detector", detector_header, detector_rows, [
        "Every detection down to score 0.1; labelled boxes whose shorter side is under `eval.min_box_px` (8 px) and "
        "objects less than a quarter visible are ignore regions, counted neither way (docs/design.md §4).",
        provenance])
    return [relations, detector], {"default_run": run.run_id}
