"""The ``adapt`` experiment's table and curves (docs/adapt.md), for ``make compare``: how the held-out domain's
scores grow with N, the number of its images labelled, per recipe.

A run is a point when its ``experiment_name`` is the sweep's (``adapt`` unless swept under another name): its
recipe (``adapt.recipe``), N (``data.sources.pool.images``) and draw (``data.sources.pool.draw``) are its logged
parameters; the newest run of each (recipe, N, draw) counts. Per (recipe, N): the mean over its draws and their
min / max. N=0 is the default run the finetune jobs started from (``adapt.base_run``): no new image, the
generator's data alone (what mixed adds images to, as well). Figures, all on the held-out test set (shift_data),
mixed subset: the end-to-end pair_f1 of the run's end-to-end method on detected boxes
(``eval.shift.detected.<export.end_to_end.method>.mixed.pair_f1``), DeepWORD's pair_f1 on ground-truth boxes
(the relation network alone), the detector's AP@0.5 per class (``detector.shift.ap50.<class>``); and the in-domain
end-to-end pair_f1 (the generator's test split: what a recipe keeps of the old domain).
"""

from __future__ import annotations

import statistics
from collections import Counter
from pathlib import Path

from deepword.scoring.report import metric_name
from pipeline.runs import RunRecord
from pipeline.tables import Table, save_figure

ADAPT_EXPERIMENT = "adapt"
RECIPE_PARAM = "adapt.recipe"
IMAGES_PARAM = "data.sources.pool.images"
FREEZE_PARAM = "init.detector_train.freeze"
DRAW_PARAM = "data.sources.pool.draw"
BASE_PARAM = "adapt.base_run"
END_TO_END_PARAM = "export.end_to_end.method"
DEFAULT_END_TO_END = "deepword_then_logic"
RECIPES = {"finetune": "finetune (default run's weights)",
           "finetune_mixed": "finetune_mixed (default run's weights, generator + N images)",
           "scratch": "scratch (N images alone)", "mixed": "mixed (generator + N images)"}
BASE_LABEL = "default run (N=0)"
TITLE = "How many images to label: held-out scores against N"
KEPT_RECIPES_NOTE = ("Rows of {recipes} kept from this page as `make compare` last wrote it: the tracking store it ran "
                     "on has no runs of them under this sweep's name (each row names the run it came from).")
CLASSES = ("vehicle", "wheel")
# (column stem, plot title); the held-out figures get mean / min / max columns, the in-domain one its mean
FIGURES = {"e2e": "held-out end-to-end pair_f1 (mixed, detected boxes)",
           "gt": "held-out DeepWORD pair_f1 (mixed, ground-truth boxes)",
           "ap50.vehicle": "held-out detector AP@0.5 vehicle", "ap50.wheel": "held-out detector AP@0.5 wheel"}
IN_DOMAIN = "in-domain e2e"


def _shift(key: str) -> str:
    return key.replace("eval.", "eval.shift.", 1)


def end_to_end_method(run: RunRecord) -> str:
    return run.param(END_TO_END_PARAM) or DEFAULT_END_TO_END


def figures(run: RunRecord) -> dict[str, float | None]:
    """The run's figures by column stem (None where it has none)."""
    method, m = end_to_end_method(run), run.metrics
    out = {"e2e": m.get(_shift(metric_name("detected", method, "mixed", "pair_f1"))),
           "gt": m.get(_shift(metric_name("gt", "deepword", "mixed", "pair_f1")))}
    out |= {f"ap50.{c}": m.get(f"detector.shift.ap50.{c}") for c in CLASSES}
    out[IN_DOMAIN] = m.get(metric_name("detected", method, "mixed", "pair_f1"))
    return out


def recipe_label(run: RunRecord) -> str | None:
    """The run's recipe, with the detector parts it kept frozen (``init.detector_train.freeze``) named: a variant of
    its own, not a point of the recipe's curve."""
    recipe = run.param(RECIPE_PARAM)
    frozen = run.param(FREEZE_PARAM) or []
    return None if recipe is None else f"{recipe} ({', '.join(frozen)} frozen)" if frozen else str(recipe)


def adapt_points(runs: list[RunRecord], experiment: str = ADAPT_EXPERIMENT,
                 base: str | None = None) -> dict[tuple[str, int, int], RunRecord]:
    """The newest evaluated run of every (recipe, N, draw) of the sweep (``runs``: newest first); with ``base``, of the
    recipes that start from a default run (finetune...) only the runs started from that one, so that a curve and its
    N=0 level share one default run."""
    points: dict[tuple[str, int, int], RunRecord] = {}
    for run in runs:
        recipe, n, draw = recipe_label(run), run.param(IMAGES_PARAM), run.param(DRAW_PARAM)
        if run.param("experiment_name") != experiment or recipe is None or n is None:
            continue
        if figures(run)["e2e"] is None:   # stopped before evaluate, or without the held-out set
            continue
        if base is not None and recipe.startswith("finetune") and base_run_id(run) != base:
            continue
        points.setdefault((recipe, int(n), int(draw or 0)), run)
    return points


def base_run_id(run: RunRecord) -> str | None:
    """The run's ``adapt.base_run`` as logged (a run id stays a string even when it reads as a number)."""
    raw = run.params.get(BASE_PARAM)
    return None if raw in (None, "", "null") else raw


def base_run(runs: list[RunRecord], points: dict) -> tuple[RunRecord | None, str | None]:
    """The default run the sweep's finetune jobs started from (the most named ``adapt.base_run``, finetune's
    first), found among ``runs``; and its id (None when no job names one)."""
    named = Counter(base_run_id(r) for (recipe, _, _), r in points.items() if recipe.startswith("finetune") and base_run_id(r))
    named = named or Counter(base_run_id(r) for r in points.values() if base_run_id(r))
    if not named:
        return None, None
    run_id = named.most_common(1)[0][0]
    return next((r for r in runs if r.run_id == run_id), None), run_id


def _summary(values: list[float]) -> tuple[float | None, float | None, float | None]:
    return (statistics.fmean(values), min(values), max(values)) if values else (None, None, None)


def header() -> list[str]:
    cols = ["Recipe", "N images", "draws"]
    for stem in FIGURES:
        cols += [f"{stem} mean", f"{stem} min", f"{stem} max"]
    return cols + [f"{IN_DOMAIN} mean", "runs"]


def adapt_table(runs: list[RunRecord], experiment: str = ADAPT_EXPERIMENT) -> tuple[Table, dict]:
    """One row per recipe and N (mean, min and max over the draws) and the N=0 row of the default run."""
    base, base_id = base_run(runs, adapt_points(runs, experiment))
    points = adapt_points(runs, experiment, base_id)
    rows, used = [], {}
    if base is not None:
        f = figures(base)
        cells = [BASE_LABEL, 0, 1]
        for stem in FIGURES:
            cells += [f[stem]] * 3
        rows.append(cells + [f[IN_DOMAIN], base.name])
        used["adapt.base"] = base.run_id
    groups: dict[tuple[str, int], list[tuple[int, RunRecord]]] = {}
    for (recipe, n, draw), run in points.items():
        groups.setdefault((recipe, n), []).append((draw, run))
        used[f"adapt.{recipe}.{n}.{draw}"] = run.run_id
    order = {r: i for i, r in enumerate(RECIPES)}
    for recipe, n in sorted(groups, key=lambda k: (order.get(k[0], len(order)), k[0], k[1])):
        members = sorted(groups[(recipe, n)], key=lambda dr: dr[0])
        cells = [RECIPES.get(recipe, recipe), n, len(members)]
        for stem in FIGURES:
            cells += list(_summary([v for _, r in members if (v := figures(r)[stem]) is not None]))
        cells.append(_summary([v for _, r in members if (v := figures(r)[IN_DOMAIN]) is not None])[0])
        rows.append(cells + [", ".join(f"draw {d}: {r.name}" for d, r in members)])
    notes = ["N counts labelled images of the new domain (its pool), split by frame into train and val (~80 / 20); "
             "every run chooses its checkpoints and the detector's operating point on that val split.",
             "Held-out test set (shift_data, the mixed subset), which no run trains on: e2e = the run's end-to-end "
             "method on detected boxes, gt = DeepWORD on ground-truth boxes; ap50 = the detector's AP@0.5; "
             f"{IN_DOMAIN} = end-to-end pair_f1 on the generator's test split. mean / min / max over the draws.",
             f"{BASE_LABEL}: the run the finetune jobs started from, trained on the generator's data alone."]
    if not points:
        notes.append(f"No rows: no evaluated run with experiment_name={experiment} (`make adapt`).")
    elif base is None:
        notes.append("No N=0 row: " + (f"the base run {base_id} is not among this experiment's finished runs."
                                       if base_id else "no job names its base run (adapt.base_run)."))
    if experiment != ADAPT_EXPERIMENT:
        notes.append(f"The sweep's runs: experiment_name={experiment}.")
    return Table(TITLE, header(), rows, notes), used


def with_earlier_recipes(table: Table, earlier: Table | None) -> Table:
    """``table`` (rows from the store's runs) with the rows of ``earlier`` (this page's adapt table as ``make compare``
    last wrote it) whose recipe it has no row of, the N=0 row too where it has none, and a note naming them: a sweep
    of one recipe (e.g. under its own ``experiment_name``) adds its curve without wiping the others'. ``table`` as it
    is where it has no rows or ``earlier`` nothing to add."""
    if earlier is None or not table.rows:
        return table
    have = {row[0] for row in table.rows}
    kept = [row for row in earlier.rows if row[0] not in have]
    if not kept:
        return table
    order = {label: i for i, label in enumerate((BASE_LABEL, *RECIPES.values()))}
    rows = sorted([*table.rows, *kept], key=lambda r: (order.get(r[0], len(order)), str(r[0]), r[1]))
    names = ", ".join(f"`{label}`" for label in dict.fromkeys(row[0] for row in kept))
    return Table(table.title, table.header, rows, [*table.notes, KEPT_RECIPES_NOTE.format(recipes=names)])


def adapt_chart(table: Table, path: Path) -> None:
    """The four held-out figures against N (log axis), one line per recipe at the mean over draws with the
    min-max band; the default run (N=0) as a dashed level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    col = {name: i for i, name in enumerate(table.header)}
    base = next((r for r in table.rows if r[0] == BASE_LABEL), None)
    recipes = list(dict.fromkeys(r[0] for r in table.rows if r[0] != BASE_LABEL))
    sizes = sorted({r[1] for r in table.rows if r[0] != BASE_LABEL})
    colours = dict(zip(RECIPES.values(), ("tab:blue", "tab:purple", "tab:orange", "tab:green"), strict=True))
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.4))
    for ax, (stem, title) in zip(axes.flat, FIGURES.items(), strict=True):
        for recipe in recipes:
            rows = sorted((r for r in table.rows if r[0] == recipe and r[col[f"{stem} mean"]] is not None),
                          key=lambda r: r[1])
            if not rows:
                continue
            x = [r[1] for r in rows]
            colour = colours.get(recipe)
            ax.plot(x, [r[col[f"{stem} mean"]] for r in rows], marker="o", color=colour, label=recipe)
            ax.fill_between(x, [r[col[f"{stem} min"]] for r in rows], [r[col[f"{stem} max"]] for r in rows],
                            color=colour, alpha=0.2, linewidth=0)
        if base is not None and base[col[f"{stem} mean"]] is not None:
            ax.axhline(base[col[f"{stem} mean"]], color="grey", linestyle="--", linewidth=1, label=BASE_LABEL)
        ax.set_xscale("log")
        if sizes:
            ax.set_xticks(sizes, [str(n) for n in sizes])
            ax.minorticks_off()
        ax.set_xlabel("N labelled images of the new domain (log scale)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    # one legend for the four panels, below them: inside a panel it hid the points that lie low (scratch's)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=9, frameon=False)
    fig.suptitle("Lines: mean over draws; bands: min to max")
    save_figure(fig, path, rect=(0, 0.07, 1, 1))
