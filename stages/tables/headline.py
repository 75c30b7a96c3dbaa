"""The README's headline: what ``make pipeline``'s default configuration gives, from the newest default run with
end-to-end rows (``stages.tables.adapt_base.is_default_run``: no sweep, the generator's data, trained from scratch,
the default settings of its profile), and, where the adapt sweep has run, what 50 labelled images of a new camera
buy with the recipe docs/adapt.md recommends (its draws started from that run, else, until the sweep runs from it,
from the default run they name, with a note saying so). ``make compare`` writes it between the README's markers."""

from __future__ import annotations

from deepword.scoring.report import metric_name
from deepword.word_format import SUBSETS
from pipeline.runs import RunRecord
from pipeline.tables import Table, between
from stages.tables.adapt import adapt_points, base_run_id, end_to_end_method
from stages.tables.adapt_base import is_default_run
from stages.tables.bev import score

HEADLINE_BEGIN = "<!-- headline by make compare: begin -->"
HEADLINE_END = "<!-- headline by make compare: end -->"
ADAPT_IMAGES = 50   # the adapt sweep's point the headline quotes: a small labelling effort
# The recipe docs/adapt.md recommends ("Which recipe"), whose point at ADAPT_IMAGES the headline quotes, and its row.
# The fine-tunings' points are those started from the headline's run; mixed trains from scratch and starts from no run.
ADAPT_RECIPE = "finetune_mixed"
ADAPT_ROWS = {"finetune": "held-out domain after fine-tuning on {n} of its images",
              "finetune_mixed": "held-out domain, the default run trained further on SynWORD and {n} of its images",
              "mixed": "held-out domain, trained on SynWORD and {n} of its images together"}


def _rows_of(run: RunRecord) -> list[tuple[str, str, str]]:
    """(label, boxes, method) of the headline's rows; ``boxes`` prefixed ``shift.`` for the held-out domain."""
    e2e = end_to_end_method(run)
    return [(f"end to end (detected boxes, `{e2e}`)", "detected", e2e),
            ("end to end, held-out domain", "shift.detected", e2e),
            ("ground-truth boxes, DeepWORD", "gt", "deepword"),
            ("ground-truth boxes, `logic` (the paper's IoU rule)", "gt", "logic"),
            ("ground-truth boxes, DeepWORD, held-out domain", "shift.gt", "deepword")]


def headline_run(runs: list[RunRecord]) -> RunRecord | None:
    """The newest default run with end-to-end rows (``runs``: newest first): the run the headline and the default
    run's full tables (stages/tables/default_run.py) quote."""
    return next((r for r in runs if metric_name("detected", end_to_end_method(r), "mixed", "pair_f1") in r.metrics
                 and is_default_run(r, r.tags.get("profile", "quick"))), None)


def headline_table(runs: list[RunRecord], adapt_experiment: str) -> tuple[Table, dict]:
    """pair_f1 on easy / hard / mixed and hard image_acc of the newest default run (``runs``: newest first) with
    end-to-end rows."""
    run = headline_run(runs)
    header = ["synthetic test images", *(f"pair_f1 {s}" for s in SUBSETS), "image_acc hard"]
    rows, notes = [], []
    if run is None:
        notes.append("No finished default run with end-to-end rows yet: run `make pipeline`, then `make compare`.")
        return Table("Headline", header, rows, notes), {"headline": None}
    m = run.metrics
    for label, boxes, method in _rows_of(run):
        cells = _cells(m, boxes, method)
        if any(c is not None for c in cells):
            rows.append([label, *cells])
    sources = {"headline": run.run_id}
    adapted, started_from = recommended_points(runs, adapt_experiment, run.run_id)
    if adapted:
        draws = [_cells(r.metrics, "shift.detected", end_to_end_method(r)) for r in adapted]
        draws_said = f"mean of {len(adapted)} draws" if len(adapted) > 1 else "one draw"
        rows.append([ADAPT_ROWS[ADAPT_RECIPE].format(n=ADAPT_IMAGES) + f" ({draws_said})",
                     *(_mean(list(column)) for column in zip(*draws, strict=True))])
        sources["headline.adapt"] = ",".join(r.run_id for r in adapted)
    ap = [m.get(f"detector.test.ap50.{c}") for c in ("vehicle", "wheel")]
    if None not in ap:
        notes.append(f"Detector test AP@0.5: vehicles {ap[0]:.1f}, wheels {ap[1]:.1f} "
                     f"(held out: {_fmt(m.get('detector.shift.ap50.vehicle'))}, "
                     f"{_fmt(m.get('detector.shift.ap50.wheel'))}).")
    bev = _bev_note(m, end_to_end_method(run))
    if bev:
        notes.append(bev)
    if adapted and started_from is not None:
        base = next((r for r in runs if r.run_id == started_from), None)
        named = (f"{base.name} ({base.tags.get('git_commit', '?')[:7]})" if base is not None else started_from)
        notes.append(f"The last row's runs started from the default run {named}, not from the one above: `make adapt` "
                     "has not run from it yet.")
    notes.append(f"Run {run.name} ({run.tags.get('git_commit', '?')[:7]}), profile {run.tags.get('profile', '?')}, "
                 f"seed {run.tags.get('seed', '?')}; every image is a synthetic render.")
    return Table("Headline", header, rows, notes), sources


def recommended_points(runs: list[RunRecord], experiment: str, headline: str) -> tuple[list[RunRecord], str | None]:
    """The recommended recipe's draws at ADAPT_IMAGES (``runs``: newest first): those started from the headline's run
    (``headline``), and None; where the sweep has none from it (a default run newer than the sweep), those started
    from the default run its newest such draw names, and that run's id."""
    def at_n(points: dict) -> list[RunRecord]:
        return [r for (recipe, n, _), r in points.items() if recipe == ADAPT_RECIPE and n == ADAPT_IMAGES]

    adapted = at_n(adapt_points(runs, experiment, headline))
    if adapted or not ADAPT_RECIPE.startswith("finetune"):
        return adapted, None
    newest = at_n(adapt_points(runs, experiment))
    base = base_run_id(newest[0]) if newest else None
    return (at_n(adapt_points(runs, experiment, base)), base) if base is not None else ([], None)


def _bev_note(metrics: dict[str, float], method: str) -> str | None:
    """The footprints of the end-to-end method, scored the nuScenes way within range (docs/bev.md), or None."""
    def scores(domain: str) -> str | None:
        values = [score(metrics, domain, "detected", method, "all", k) for k in ("ap", "ate_m", "aoe_deg", "aoe180_deg")]
        if None in values:
            return None
        ap, ate, aoe, aoe180 = values
        return f"AP {ap:.1f}, ATE {ate:.2f} m, AOE {aoe:.1f}° over 360° ({aoe180:.1f}° modulo 180°)"
    here, held_out = scores(""), scores("shift.")
    if here is None:
        return None
    return (f"Bird's-eye view, end to end, every vehicle within range: {here}"
            + (f"; held out: {held_out}." if held_out else "."))


def _cells(metrics: dict[str, float], boxes: str, method: str) -> list[float | None]:
    """A row's cells: pair_f1 on each subset, then hard image_acc (None where not logged)."""
    return [*(metrics.get(metric_name(boxes, method, s, "pair_f1")) for s in SUBSETS),
            metrics.get(metric_name(boxes, method, "hard", "image_acc"))]


def _mean(values: list[float | None]) -> float | None:
    return None if not values or any(v is None for v in values) else sum(values) / len(values)


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f}"


def keep_adapt_row(headline: Table, readme) -> Table:
    """The headline with the adapt sweep's row the README shows, where this store has no adapt runs."""
    shown = between(readme.read_text(), HEADLINE_BEGIN, HEADLINE_END) if readme.is_file() else None
    if shown is None or not headline.rows:
        return headline
    prefix = ADAPT_ROWS[ADAPT_RECIPE].split("{n}")[0]
    kept = [row for row in Table.from_markdown("# Headline\n" + shown).rows if str(row[0]).startswith(prefix)]
    if not kept:
        return headline
    note = "The last row is kept from the README: the tracking store `make compare` ran on has no adapt runs."
    return Table(headline.title, headline.header, [*headline.rows, *kept], [*headline.notes[:-1], note, headline.notes[-1]])


def write_headline(page, table: Table) -> None:
    """Replace the section of ``page`` between HEADLINE_BEGIN and HEADLINE_END with ``table`` (without its title:
    the page gives it one). A page without the markers is an error: the README decides where its headline goes."""
    text = page.read_text()
    if HEADLINE_BEGIN not in text or HEADLINE_END not in text:
        raise SystemExit(f"error: {page} has no headline markers ({HEADLINE_BEGIN} ... {HEADLINE_END})")
    before, rest = text.split(HEADLINE_BEGIN, 1)
    after = rest.split(HEADLINE_END, 1)[1]
    body = table.markdown().split("\n", 2)[2]   # drop the "## Headline" line and the blank line after it
    page.write_text(before + HEADLINE_BEGIN + "\n" + body.rstrip("\n") + "\n" + HEADLINE_END + after)
