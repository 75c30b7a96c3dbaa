"""``make compare`` (``python -m stages.tables``): the paper's Tables 1-3, and DeepWORD against ``logic_plus``
over several datasets, from the pipeline's runs in MLflow.

Each table row is a configuration given by its Hydra overrides (``rows.py``); a run is that row when its
logged parameters equal the row's composed configuration (``RowMatcher``), whichever command produced it
(a sweep of ``make ablations`` or a single run); the newest such run is used. Writes
``table{1,2,3}.{md,csv}``, ``comparison.md`` and ``comparison.png`` (our numbers beside the paper's,
``deepword.paper``), ``datasets.{md,csv,png}`` (the ``datasets`` sweep: one row per root seed),
``default_run.md``, ``default_run.csv``, ``default_run_detector.csv`` (the headline's run in full: every relation
method on both box sources, in domain and held out, and the detector; ``stages.tables.default_run``),
``bev.md``, ``bev.csv``, ``bev_populations.csv``, ``bev_roles.csv`` (the footprints scored the nuScenes way, per
method and per wheel population, and the wheels' roles, of the newest run with them; ``stages.tables.bev``),
``adapt.{md,csv,png}`` (the ``adapt`` sweep: held-out scores against the number of new-domain images labelled, per recipe; ``stages.tables.adapt``), logs them as
artifacts of a run named ``comparison`` (tag ``kind=comparison``) in the same experiment, and with
``--results FILE`` writes the tables and charts, with the commit and date of every run, into that page.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

from deepword import paper
from deepword.scoring.report import metric_name
from deepword.word_format import SUBSETS
from pipeline.runs import RunRecord, load_runs
from pipeline.tables import (
    NOT_AVAILABLE,
    Table,
    between,
    fmt,
    paired_difference,
    save_figure,
    tables_in_markdown,
)
from stages.tables.adapt import ADAPT_EXPERIMENT, adapt_chart, adapt_table, with_earlier_recipes
from stages.tables.adapt_base import is_default_run
from stages.tables.bev import bev_tables
from stages.tables.default_run import default_run_tables
from stages.tables.headline import headline_table, keep_adapt_row, write_headline
from stages.tables.rows import TABLE1, TABLE2, TABLE3_ROW, Row, RowMatcher

COMPARISON_TAG = "kind"
COMPARISON_KIND = "comparison"
RESULTS_BEGIN = "<!-- measured by make compare: begin -->"
RESULTS_END = "<!-- measured by make compare: end -->"

TABLE3_METHODS = {"logic": "Logic model", "logic_plus": "Logic+ (ours)", "prior": "GMM prior (ours)",
                  "deepword": "DeepWORD", "deepword_int8": "DeepWORD INT8 (ours)"}

ACC_METRIC = metric_name("gt", "deepword", "mixed", "wheel_acc")
IMAGE_ACC_METRIC = metric_name("gt", "deepword", "mixed", "image_acc")
LATENCY_METRIC = "export.relation.ms_per_img_b1"
PARAMS_METRIC = "relation.params"


def pick(runs: list[RunRecord], row: Row, needed: str, matcher: RowMatcher,
         experiment: str | None = None) -> RunRecord | None:
    """The newest run of ``row``'s configuration that has the metric ``needed``; with ``experiment``, a run
    of that sweep first (its rows share one training budget), else any run of the row, a default run
    (``adapt_base.is_default_run``) before a variant of it that the row's keys do not tell apart."""
    found = [run for run in runs if needed in run.metrics and matcher.matches(row, run)]  # newest first
    found.sort(key=lambda run: not is_default_run(run, run.tags.get("profile", "quick")))  # stable: newest first
    own = [run for run in found if run.param("experiment_name") == experiment]
    return (own or found or [None])[0]


def provenance(run: RunRecord | None) -> str:
    """A run's name, commit and date, as a table cell."""
    if run is None:
        return NOT_AVAILABLE
    date = datetime.fromtimestamp(run.start_time / 1000, UTC).strftime("%Y-%m-%d")
    return f"{run.name} ({run.tags.get('git_commit', '?')[:7]}, {date})"


def backbone_table(title: str, rows: tuple[Row, ...], runs: list[RunRecord], experiment: str,
                   matcher: RowMatcher) -> tuple[Table, dict]:
    header = ["Row", "params", "ms/img b1 (ours)", "ms/img b1 (paper)", "wheel_acc mixed (ours)",
              "image_acc mixed (ours)", "accuracy (paper)", "run (commit, date)"]
    out, used = [], {}
    for row in rows:
        run = pick(runs, row, ACC_METRIC, matcher, experiment)
        m = run.metrics if run else {}
        params = m.get(PARAMS_METRIC)
        out.append([row.label, None if params is None else int(params), m.get(LATENCY_METRIC), None,
                    m.get(ACC_METRIC), m.get(IMAGE_ACC_METRIC), None, provenance(run)])
        used[row.label] = run.run_id if run else None
    notes = ["Ours: ground-truth boxes, mixed test subset (docs/design.md §7); latency: onnxruntime, batch 1, "
             "this machine.",
             "Paper column n/a: the paper's figures for this table are not transcribed here (unverified).",
             "A row shows n/a when no finished run of its configuration with evaluation metrics is in "
             "the experiment: run `make ablations`."]
    return Table(title, header, out, notes), used


def table3(runs: list[RunRecord], matcher: RowMatcher) -> tuple[Table, dict]:
    needed = metric_name("gt", "logic", "mixed", "wheel_acc")
    run = pick(runs, TABLE3_ROW, needed, matcher, "table3")
    m = run.metrics if run else {}
    header = ["Method"]
    for s in SUBSETS:
        header += [f"{s} wheel_acc (ours)", f"{s} image_acc (ours)", f"{s} accuracy (paper)"]
    rows = []
    for method, label in TABLE3_METHODS.items():
        cells = [label]
        for s in SUBSETS:
            cells += [m.get(metric_name("gt", method, s, "wheel_acc")), m.get(metric_name("gt", method, s, "image_acc")),
                      paper.TABLE3_ACCURACY.get(method, {}).get(s)]
        if any(c is not None for c in cells[1:]):
            rows.append(cells)
    notes = [f"Ours: run {provenance(run)}, id {run.run_id}, ground-truth boxes." if run else
             "No finished run with evaluation metrics: run `make ablations` (or `make pipeline`).",
             "The paper does not say whether its accuracy is per wheel or per image: both are shown."]
    return Table("Table 3: logic model vs DeepWORD on easy / hard / mixed", header, rows, notes), \
        {"table3": run.run_id if run else None}


DATASETS_EXPERIMENT = "datasets"
DATASETS_METHODS = {"deepword": "DeepWORD", "logic_plus": "logic_plus"}
DATASETS_SUBSETS = ("hard", "mixed")
DATASETS_METRICS = ("wheel_acc", "image_acc")
DATASETS_SUMMARY_ROWS = 2  # the datasets table ends with the ahead/level/behind and the difference rows


def _datasets_column(subset: str, metric: str, method: str) -> str:
    return f"{subset} {metric} {DATASETS_METHODS[method]}"


def datasets_table(runs: list[RunRecord], experiment: str = DATASETS_EXPERIMENT) -> tuple[Table, dict]:
    """One row per dataset (root seed) of the ``datasets`` sweep (``experiment``: its ``experiment_name``, so a
    variant swept under a name of its own is tabulated on its own), the newest evaluated run of each: DeepWORD
    and ``logic_plus`` on hard and mixed (ground-truth boxes), then their mean over the datasets, on how
    many datasets DeepWORD is ahead / level / behind, and the mean paired difference with its standard error
    (whether a difference is larger than the spread from one dataset to the next)."""
    needed = metric_name("gt", "deepword", "hard", "wheel_acc")
    newest: dict[int, RunRecord] = {}
    for run in runs:  # newest first
        if run.param("experiment_name") == experiment and needed in run.metrics:
            newest.setdefault(int(run.param("seed")), run)
    keys = [(s, m, method) for s in DATASETS_SUBSETS for m in DATASETS_METRICS for method in DATASETS_METHODS]
    header = ["Dataset (seed)"] + [_datasets_column(*k) for k in keys] + ["run (commit, date)"]
    rows, used = [], {}
    for seed in sorted(newest):
        run = newest[seed]
        rows.append([str(seed)] + [run.metrics.get(metric_name("gt", method, s, m)) for s, m, method in keys]
                    + [provenance(run)])
        used[f"datasets.{seed}"] = run.run_id
    if rows:
        columns = list(zip(*[row[1:-1] for row in rows], strict=True))
        rows.append([f"mean of {len(newest)}"]
                    + [None if None in col else statistics.fmean(col) for col in columns] + [""])
        tally, difference = ["DeepWORD ahead / level / behind"], ["DeepWORD - logic_plus (± s.e.)"]
        for s in DATASETS_SUBSETS:
            for m in DATASETS_METRICS:
                ours, theirs = (1 + keys.index((s, m, method)) for method in DATASETS_METHODS)
                pairs = [(r[ours], r[theirs]) for r in rows[:-1] if r[ours] is not None and r[theirs] is not None]
                counts = (sum(a > b for a, b in pairs), sum(a == b for a, b in pairs), sum(a < b for a, b in pairs))
                tally += ["/".join(map(str, counts)), ""]
                difference += [paired_difference([a - b for a, b in pairs]), ""]
        rows += [tally + [""], difference + [""]]  # the DATASETS_SUMMARY_ROWS rows
    notes = ["Ground-truth boxes, the default configuration on every dataset (`make datasets`: "
             "`experiment=datasets`, one root seed per dataset: other scenes, other splits).",
             "A quick-profile test set holds ~800 evaluated hard wheels: 0.12 points of hard wheel_acc is one wheel.",
             f"No rows: no evaluated run with experiment_name={experiment} (`make datasets`)." if not newest else
             f"Newest run per seed with experiment_name={experiment}; seeds {sorted(newest)}."]
    title = "DeepWORD vs logic_plus over datasets" + ("" if experiment == DATASETS_EXPERIMENT else f" ({experiment})")
    return Table(title, header, rows, notes), used


def datasets_chart(table: Table, path: Path) -> None:
    """Hard wheel_acc and image_acc per dataset, DeepWORD beside logic_plus, with their means."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = table.rows[:-DATASETS_SUMMARY_ROWS]  # the datasets and their mean
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for ax, metric in zip(axes, DATASETS_METRICS, strict=True):
        x = np.arange(len(rows))
        low = 100.0
        for i, (method, colour) in enumerate((("deepword", "tab:blue"), ("logic_plus", "tab:orange"))):
            col = table.header.index(_datasets_column("hard", metric, method))
            values = np.array([np.nan if r[col] is None else r[col] for r in rows], dtype=float)
            low = min(low, np.nanmin(values)) if np.isfinite(values).any() else low
            ax.bar(x + (i - 0.5) * 0.38, values, 0.38, color=colour, label=DATASETS_METHODS[method])
            for xi, v in zip(x, values, strict=True):
                if np.isfinite(v):
                    ax.text(xi + (i - 0.5) * 0.38, v + 0.05, f"{v:.2f}", ha="center", fontsize=7, rotation=90)
        ax.set_xticks(x, [r[0].replace(" of ", "\nof ") for r in rows])  # "mean\nof 10" fits one bar's width
        ax.axvline(len(rows) - 1.5, color="grey", linestyle="--", linewidth=0.8)  # datasets | their mean
        ax.set_ylim(max(0.0, np.floor(low) - 1), 100.6)  # headroom for the value labels
        ax.set_yticks([t for t in ax.get_yticks() if t <= 100])
        ax.set_title(f"hard {metric} (ground-truth boxes)")
        ax.set_xlabel("dataset (root seed)")
        ax.legend(loc="lower left", fontsize=8)
    save_figure(fig, path)


def bar_chart(tables: list[Table], path: Path) -> None:
    """One panel per table: our accuracy beside the paper's where the paper's is known."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    for ax, table in zip(axes[:2], tables[:2], strict=True):
        labels = [r[0] for r in table.rows]
        ours = [np.nan if r[4] is None else r[4] for r in table.rows]
        ax.bar(labels, ours, color="tab:blue", label="ours (wheel_acc, mixed)")
        for i, v in enumerate(ours):
            ax.text(i, 1 if np.isnan(v) else v + 1, NOT_AVAILABLE if np.isnan(v) else f"{v:.1f}",
                    ha="center", fontsize=8)
        ax.set_title(table.title.split(":")[0] + " (paper: n/a)")
        ax.set_xlim(-0.6, len(labels) - 0.4)  # rows without a run (n/a) keep their place on the axis
        ax.set_ylim(0, 118)
        ax.set_ylabel("accuracy (%)")
        ax.tick_params(axis="x", rotation=30)
        ax.legend(loc="upper left", fontsize=8)
    ax = axes[2]
    t3 = {r[0]: r for r in tables[2].rows}
    x = np.arange(len(SUBSETS))
    bars = [(f"{TABLE3_METHODS[m]} {who}", m, who) for m in ("logic", "deepword") for who in ("ours", "paper")]
    width = 0.8 / len(bars)
    colours = {"logic": ("tab:orange", "navajowhite"), "deepword": ("tab:blue", "lightsteelblue")}
    for i, (label, method, who) in enumerate(bars):
        row = t3.get(TABLE3_METHODS[method])
        values = [np.nan] * len(SUBSETS)
        if who == "paper":
            values = [paper.TABLE3_ACCURACY[method][s] for s in SUBSETS]
        elif row is not None:
            values = [np.nan if row[1 + 3 * j] is None else row[1 + 3 * j] for j in range(len(SUBSETS))]
        ax.bar(x + (i - (len(bars) - 1) / 2) * width, values, width,
               color=colours[method][0 if who == "ours" else 1], label=label)
    ax.set_xticks(x, SUBSETS)
    ax.set_ylim(0, 118)
    ax.set_title("Table 3: wheel_acc (ours) vs accuracy (paper)")
    ax.legend(loc="upper left", fontsize=8, ncol=2)
    save_figure(fig, path)


def compare(uri: str, experiment: str, out_dir: Path, profile: str | None = None, log: bool = True,
            datasets_experiment: str = DATASETS_EXPERIMENT, results: Path | None = None,
            adapt_experiment: str = ADAPT_EXPERIMENT, readme: Path | None = None) -> dict:
    """Build the tables from ``experiment`` in ``uri``, write them under ``out_dir``, log them, and (with
    ``results``) write them into that Markdown page; the datasets table from the runs whose experiment_name is
    ``datasets_experiment``, the adapt table and curves from those whose experiment_name is ``adapt_experiment``;
    with ``readme``, the headline table (stages/tables/headline.py) between that page's headline markers."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        raise SystemExit(f"error: no MLflow experiment {experiment!r} in {uri}; run the pipeline first")
    runs = load_runs(client, found.experiment_id, profile, exclude_tags={COMPARISON_TAG: COMPARISON_KIND})
    matcher = RowMatcher()
    t1, used1 = backbone_table("Table 1: relation backbones", TABLE1, runs, "table1", matcher)
    t2, used2 = backbone_table("Table 2: ablations (Conv+fc)", TABLE2, runs, "table2", matcher)
    t3, used3 = table3(runs, matcher)
    td, used_datasets = datasets_table(runs, datasets_experiment)
    tbs, used_bev = bev_tables(runs)
    ta, used_adapt = adapt_table(runs, adapt_experiment)
    th, used_headline = headline_table(runs, adapt_experiment)
    tdr, used_default = default_run_tables(runs)
    # a table this store has no runs for keeps what the page shows (another store's runs, e.g. a sweep run elsewhere)
    earlier = measured_tables(results) if results is not None else {}
    t1, t2, t3, td, ta = (keep_earlier(t, used, earlier) for t, used in
                          ((t1, used1), (t2, used2), (t3, used3), (td, used_datasets),
                           (ta, {k: v for k, v in used_adapt.items() if k != "adapt.base"})))   # the sweep's own runs
    ta = with_earlier_recipes(ta, earlier.get(ta.title)) if KEPT_NOTE not in ta.notes else ta
    tbs = [keep_earlier(t, used_bev, earlier) for t in tbs]
    tdr = [keep_earlier(t, used_default, earlier) for t in tdr]
    if readme is not None and "headline.adapt" not in used_headline:
        th = keep_adapt_row(th, readme)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "headline.md").write_text(th.markdown())
    tables = [t1, t2, t3]
    for i, table in enumerate(tables, start=1):
        (out_dir / f"table{i}.md").write_text(table.markdown())
        table.write_csv(out_dir / f"table{i}.csv")
    scope = f"profile {profile}" if profile else "all profiles"
    (out_dir / "comparison.md").write_text(
        f"# DeepWORD: our runs vs the paper\n\nExperiment `{experiment}` at `{uri}`, {scope}.\n\n"
        + "\n".join(t.markdown() for t in [*tdr, *tables, td, *tbs, ta]))
    (out_dir / "default_run.md").write_text("\n".join(t.markdown() for t in tdr))
    for name, table in zip(("default_run", "default_run_detector"), tdr, strict=True):
        table.write_csv(out_dir / f"{name}.csv")
    (out_dir / "bev.md").write_text("\n".join(t.markdown() for t in tbs))
    for name, table in zip(("bev", "bev_populations", "bev_roles"), tbs, strict=False):
        table.write_csv(out_dir / f"{name}.csv")
    bar_chart(tables, out_dir / "comparison.png")
    (out_dir / "datasets.md").write_text(td.markdown())
    td.write_csv(out_dir / "datasets.csv")
    if used_datasets or KEPT_NOTE in td.notes:
        datasets_chart(td, out_dir / "datasets.png")
    else:  # no stale chart beside a table that has no rows
        (out_dir / "datasets.png").unlink(missing_ok=True)
    (out_dir / "adapt.md").write_text(ta.markdown())
    ta.write_csv(out_dir / "adapt.csv")
    if used_adapt or KEPT_NOTE in ta.notes:
        adapt_chart(ta, out_dir / "adapt.png")
    else:
        (out_dir / "adapt.png").unlink(missing_ok=True)
    sources = ({f"table1.{k}": v for k, v in used1.items()} | {f"table2.{k}": v for k, v in used2.items()} | used3
               | used_datasets | used_bev | used_adapt | used_headline | used_default)
    result = {"out_dir": str(out_dir), "sources": sources, "runs_considered": len(runs), "run_id": None}
    if results is not None:
        write_results_page(results, [th, *tdr, *tables, td, *tbs, ta], out_dir, scope)
    if readme is not None:
        write_headline(readme, th)
    if log:
        run = client.create_run(found.experiment_id, run_name="comparison",
                                tags={COMPARISON_TAG: COMPARISON_KIND, "profile": profile or "all"})
        client.log_batch(run.info.run_id, params=[_param(k, v) for k, v in sources.items()])
        client.log_artifacts(run.info.run_id, str(out_dir))
        client.set_terminated(run.info.run_id)
        result["run_id"] = run.info.run_id
    return result


KEPT_NOTE = ("Kept from this page as `make compare` last wrote it: the tracking store it ran on now has no runs for "
             "this table (each row names the run, commit and date it came from).")


def measured_tables(page: Path) -> dict[str, Table]:
    """The tables of ``page``'s measured section (between RESULTS_BEGIN and RESULTS_END), by title."""
    section = between(page.read_text(), RESULTS_BEGIN, RESULTS_END) if page.is_file() else None
    return tables_in_markdown(section) if section is not None else {}


def keep_earlier(table: Table, used: dict, earlier: dict[str, Table]) -> Table:
    """``table``, or where none of its rows came from a run (``used``: row -> run id) the page's earlier table of
    that title with ``KEPT_NOTE``: a store without a sweep's runs does not wipe what another store measured."""
    before = earlier.get(table.title)
    def shown(rows):
        return [[fmt(c) for c in row] for row in rows]

    if any(used.values()) or before is None or shown(before.rows) == shown(table.rows):
        return table
    return Table(before.title, before.header, before.rows, [*(n for n in before.notes if n != KEPT_NOTE), KEPT_NOTE])


def _head_commit() -> str:
    """The working tree's commit (short), or "unknown" outside a git checkout."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
                             cwd=Path(__file__).parent)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def write_results_page(page: Path, tables: list[Table], out_dir: Path, scope: str) -> None:
    """Replace the measured section of ``page`` (between RESULTS_BEGIN and RESULTS_END; appended when
    absent) with the tables and charts, copied next to it into ``<page stem>/``."""
    charts = page.parent / page.stem
    charts.mkdir(parents=True, exist_ok=True)
    images = [name for name in ("comparison.png", "datasets.png", "adapt.png") if (out_dir / name).is_file()]
    for name in images:
        shutil.copyfile(out_dir / name, charts / name)
    today = datetime.now(UTC).strftime("%Y-%m-%d")
    section = [RESULTS_BEGIN, "", f"Written by `make compare` on {today} at commit `{_head_commit()}` from the runs "
               f"in MLflow ({scope}); every row names the run, commit and date it comes from.", ""]
    section += [t.markdown(level=3) for t in tables]
    section += [f"![{name}]({charts.name}/{name})" for name in images]
    section += ["", RESULTS_END]
    text = page.read_text() if page.is_file() else "# Results\n\n"
    if RESULTS_BEGIN in text and RESULTS_END in text:
        before, rest = text.split(RESULTS_BEGIN, 1)
        after = rest.split(RESULTS_END, 1)[1]
        text = before + "\n".join(section) + after
    else:
        text = text.rstrip("\n") + "\n\n" + "\n".join(section) + "\n"
    page.write_text(text)


def _param(key: str, value):
    from mlflow.entities import Param

    return Param(f"source.{key}".replace("+", "plus"), value or NOT_AVAILABLE)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m stages.tables", description=__doc__.split("\n")[0])
    parser.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"))
    parser.add_argument("--experiment", default="deepword")
    parser.add_argument("--profile", default=None, help="only runs of this profile (default: all)")
    parser.add_argument("--out", type=Path, default=Path("outputs/comparison"))
    parser.add_argument("--results", type=Path, default=None, metavar="PAGE",
                        help="also write the tables and charts into this Markdown page (make compare: docs/results.md)")
    parser.add_argument("--readme", type=Path, default=None, metavar="PAGE",
                        help="also write the headline table between this page's headline markers (make compare: README.md)")
    parser.add_argument("--no-log", action="store_true", help="do not log a comparison run to MLflow")
    parser.add_argument("--datasets", default=DATASETS_EXPERIMENT, metavar="NAME",
                        help="the datasets table from the runs with experiment_name=NAME (default: %(default)s)")
    parser.add_argument("--adapt", default=ADAPT_EXPERIMENT, metavar="NAME",
                        help="the adapt table and curves from the runs with experiment_name=NAME (default: %(default)s)")
    args = parser.parse_args(argv)
    result = compare(args.tracking_uri, args.experiment, args.out, args.profile, log=not args.no_log,
                     datasets_experiment=args.datasets, results=args.results, adapt_experiment=args.adapt,
                     readme=args.readme)
    print((args.out / "comparison.md").read_text())
    print(f"wrote {args.out}/headline.md, table{{1,2,3}}.{{md,csv}}, datasets.{{md,csv,png}}, adapt.{{md,csv,png}}, comparison.md, "
          "comparison.png"
          + (f", {args.results}" if args.results else "") + (f", {args.readme}" if args.readme else "")
          + (f"; MLflow run {result['run_id']}" if result["run_id"] else ""), file=sys.stderr)
