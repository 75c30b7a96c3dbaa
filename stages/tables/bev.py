"""The bird's-eye-view tables of ``make compare`` (docs/bev.md, "Scoring"), from the newest default run with footprint
metrics (the newest run with them where no default run has them): the nuScenes-style detection scores of every vehicle within range per box source and method, in domain and
on the held-out domain, with the paired median of the vehicles that show two same-side wheels beside them (the
figure earlier runs reported, so that the history reads on); then the end-to-end method's scores per wheel
population and distance bin; then how often the wheels' front / rear roles are right."""

from __future__ import annotations

from pipeline.runs import RunRecord
from pipeline.tables import Table
from stages.tables.adapt import end_to_end_method
from stages.tables.adapt_base import is_default_run

METHODS = {"box_bottom": "box bottom (no relation)", "logic": "`logic` (the paper's IoU rule)",
           "logic_plus": "`logic_plus`", "deepword": "DeepWORD", "deepword_then_logic": "`deepword_then_logic`"}
DOMAINS = {"": "in domain", "shift.": "held out"}
BOXES = {"gt": "ground truth", "detected": "detected"}
# (metric key, column): the detection scores of one subset (design.md §7).
SCORES = (("ap", "AP (%)"), ("ate_m", "ATE (m)"), ("ase", "ASE"), ("aoe_deg", "AOE 360° (°)"),
          ("aoe180_deg", "AOE mod 180° (°)"), ("recall", "recall (%)"), ("precision", "precision (%)"),
          ("recall_at_p95", "recall at 95 % precision (%)"))
PAIRED = ("paired", "center_err_m", "median centre error, two same-side wheels (m)")
SUBSETS = {"all": "all within range", "two_wheels": "two wheels", "one_wheel": "one wheel", "no_wheel": "no wheel",
           "0-5m": "0–5 m", "5-10m": "5–10 m", "10-20m": "10–20 m"}
SUBSET_SCORES = (("vehicles", "vehicles"), ("ap", "AP (%)"), ("ate_m", "ATE (m)"),
                 ("center_err_median_m", "median centre error (m)"), ("aoe_deg", "AOE 360° (°)"),
                 ("recall", "recall (%)"), ("precision", "precision (%)"))
NEEDED = "bev.gt.deepword.all.ap"


def score(metrics: dict[str, float], domain: str, boxes: str, method: str, subset: str, key: str) -> float | None:
    """One footprint score of a run, ``bev.[shift.]<boxes>.<method>.<subset>.<metric>`` (design.md §7), or None."""
    return metrics.get(f"bev.{domain}{boxes}.{method}.{subset}.{key}")


def bev_tables(runs: list[RunRecord]) -> tuple[list[Table], dict]:
    """The two tables of the newest default run (``runs``: newest first) with footprint detection scores, else of the
    newest run with them: a variant run after the default one (``detector.facing=true``) does not take its place."""
    scored = [r for r in runs if NEEDED in r.metrics]
    run = next((r for r in scored if is_default_run(r, r.tags.get("profile", "quick"))), scored[0] if scored else None)
    m = run.metrics if run else {}
    header = ["Domain", "Boxes", "Method", *(label for _, label in SCORES), PAIRED[2]]
    rows = []
    for domain, domain_label in DOMAINS.items():
        for boxes, boxes_label in BOXES.items():
            for method, label in METHODS.items():
                cells = [score(m, domain, boxes, method, "all", k) for k, _ in SCORES]
                cells.append(score(m, domain, boxes, method, *PAIRED[:2]))
                if any(c is not None for c in cells):
                    rows.append([domain_label, boxes_label, label, *cells])
    if run is None:
        notes = ["No finished run with footprint scores: run `make pipeline` on a dataset with calibration."]
        return [Table("Bird's-eye view, scored the nuScenes way", header, rows, notes)], {"bev": None}
    notes = [f"Run {run.name} ({run.tags.get('git_commit', '?')[:7]}), id {run.run_id}: every frame's footprints (its "
             "cameras fused) against its true vehicles within the run's `bev.max_range_m` of the vehicle frame's origin. "
             "AP: the mean over 0.5 / 1 / 2 / 4 m centre distance; ATE, ASE, AOE: at 2 m, averaged over recall as "
             "nuScenes does; AOE over 360° (front and back told apart) and modulo 180°; recall and precision at 2 m of "
             "every footprint, and the recall at the lowest confidence threshold whose footprints are 95 % precise.",
             "The last column is the paired median of the vehicles with two visible same-side wheels, as earlier "
             "runs reported it (docs/bev.md, \"Scoring\")."]
    main = Table("Bird's-eye view, scored the nuScenes way", header, rows, notes)

    e2e = end_to_end_method(run)
    header = ["Vehicles", *(f"{label} {d}" for d in DOMAINS.values() for _, label in SUBSET_SCORES)]
    rows = []
    for subset, label in SUBSETS.items():
        cells = [_count(score(m, domain, "detected", e2e, subset, k), k) for domain in DOMAINS for k, _ in SUBSET_SCORES]
        if any(c is not None for c in cells):
            rows.append([label, *cells])
    populations = Table(f"Bird's-eye view, end to end (`{e2e}` on detected boxes), by wheels seen and distance",
                        header, rows,
                        ["The wheel populations: by the most of a vehicle's wheels annotated in one of the frame's "
                         "images, within range; the distance bins by the vehicle's range. Same run as above."])
    return [main, populations, roles_table(m, e2e)], {"bev": run.run_id}


# (metric key under bev.[shift.]<boxes>.roles., column): design.md §12
ROLE_SCORES = (("relations", "true relations"), ("acc", "as `deepword infer` writes them (%)"),
               ("footprint_share", "read from the footprint (% of them)"),
               ("facing_acc", "from the facing vector alone (%)"), ("network_acc", "as the relation method names them (%)"))


def roles_table(m: dict[str, float], e2e: str) -> Table:
    """How often the wheels' front / rear roles are right: as ``deepword infer`` writes them (read from the vehicle's
    footprint, else its facing vector), from the facing vector alone, and as the relation method named them."""
    rows = []
    for domain, domain_label in DOMAINS.items():
        for boxes, boxes_label in BOXES.items():
            cells = [_count(m.get(f"bev.{domain}{boxes}.roles.{k}"), k) for k, _ in ROLE_SCORES]
            if any(c is not None for c in cells):
                method = e2e if boxes == "detected" else "deepword"
                rows.append([domain_label, boxes_label, f"`{method}`", *cells])
    return Table("Wheel roles (front / rear)", ["Domain", "Boxes", "Method", *(label for _, label in ROLE_SCORES)],
                 rows, ["Over the predicted relations that name a true relation whose role is known; the method is "
                        "the one `deepword infer` runs on those boxes by default (docs/bev.md, \"The wheels' roles, "
                        "read back from the front\"). Same run as above."])


def _count(value: float | None, key: str) -> float | int | None:
    """A count as a whole number (MLflow stores every metric as a float)."""
    return int(value) if key in ("vehicles", "relations") and value is not None else value
