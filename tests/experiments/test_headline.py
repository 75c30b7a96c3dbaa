"""make compare's README headline (stages/tables/headline.py): the newest default run's end-to-end and
ground-truth rows, the adapt sweep's fine-tuned point at N=50, and the README's markers."""

from __future__ import annotations

import pytest

from pipeline.runs import RunRecord
from pipeline.tracker import flatten_params
from stages.tables.headline import HEADLINE_BEGIN, HEADLINE_END, headline_table, write_headline
from tests.experiments.pipeline_runs import compose_config

SUBSETS = ("easy", "hard", "mixed")


def _metrics(base: float) -> dict[str, float]:
    m = {}
    for i, s in enumerate(SUBSETS):
        m[f"eval.detected.deepword_then_logic.{s}.pair_f1"] = base + i
        m[f"eval.shift.detected.deepword_then_logic.{s}.pair_f1"] = base - 10 + i
        m[f"eval.gt.deepword.{s}.pair_f1"] = 99.0
        m[f"eval.gt.logic.{s}.pair_f1"] = 90.0
    m["eval.detected.deepword_then_logic.hard.image_acc"] = 40.0
    m |= {"detector.test.ap50.vehicle": 80.0, "detector.test.ap50.wheel": 88.5,   # and what a default run has
          "detector.shift.ap50.vehicle": 70.0, "eval.shift.gt.deepword.mixed.pair_f1": 98.0}
    return m


QUICK = {"profile": "quick"}


def _default_params() -> dict[str, str]:
    return flatten_params(compose_config([]))


def test_the_headline_is_the_newest_default_run_with_end_to_end_rows():
    params = _default_params()
    ablation = flatten_params(compose_config(["ablation=no_gat"]))
    runs = [RunRecord("abl", "ablation", 3, ablation, _metrics(10.0), QUICK),       # newest, but not the default
            RunRecord("gt_only", "table3", 2, params, {"eval.gt.deepword.mixed.pair_f1": 99.0}, QUICK),
            RunRecord("new", "default", 1, params, _metrics(80.0), {"git_commit": "abcdef0"} | QUICK),
            RunRecord("old", "default", 0, params, _metrics(50.0), QUICK)]
    table, sources = headline_table(runs, "adapt")
    assert sources == {"headline": "new"}
    rows = {row[0]: row[1:] for row in table.rows}
    e2e = rows["end to end (detected boxes, `deepword_then_logic`)"]
    assert e2e == [80.0, 81.0, 82.0, 40.0]
    assert rows["end to end, held-out domain"][:3] == [70.0, 71.0, 72.0]
    assert rows["ground-truth boxes, `logic` (the paper's IoU rule)"][:3] == [90.0, 90.0, 90.0]
    assert rows["ground-truth boxes, DeepWORD, held-out domain"] == [None, None, 98.0, None]   # n/a where not logged
    assert any("vehicles 80.0, wheels 88.5" in n for n in table.notes)


def test_the_headline_quotes_the_end_to_end_footprints_scored_the_nuscenes_way():
    params = _default_params()
    bev = {f"bev.{d}detected.deepword_then_logic.all.{k}": v for d, scale in (("", 1.0), ("shift.", 0.5))
           for k, v in (("ap", 80.0 * scale), ("ate_m", 0.25 / scale), ("aoe_deg", 40.0), ("aoe180_deg", 5.0))}
    table, _ = headline_table([RunRecord("new", "default", 1, params, _metrics(80.0) | bev, QUICK)], "adapt")
    assert ("Bird's-eye view, end to end, every vehicle within range: AP 80.0, ATE 0.25 m, AOE 40.0° over 360° "
            "(5.0° modulo 180°); held out: AP 40.0, ATE 0.50 m") in " ".join(table.notes)
    table, _ = headline_table([RunRecord("new", "default", 1, params, _metrics(80.0), QUICK)], "adapt")
    assert not any("Bird's-eye" in n for n in table.notes)   # a run without the bev stage: no such line


def test_a_default_run_sized_to_its_host_is_still_the_default():
    params = _default_params()
    assert params["detector.epochs"] == "auto"
    sized = params | {"detector.epochs": "49", "sized.detector.epochs": "49"}
    given = params | {"detector.epochs": "49"}   # asked for 49 epochs: not the default
    runs = [RunRecord("given", "default", 2, given, _metrics(60.0), QUICK),
            RunRecord("sized", "default", 1, sized, _metrics(70.0), QUICK)]
    assert headline_table(runs, "adapt")[1] == {"headline": "sized"}
    cap = params["detector.sizing.max_epochs"]
    pinned = params | {"detector.epochs": cap}   # the most auto may choose, set outright: the same budget
    runs.insert(0, RunRecord("pinned", "default", 3, pinned, _metrics(65.0), QUICK))
    assert headline_table(runs, "adapt")[1] == {"headline": "pinned"}
    # sized under another rule (minutes, floor): its epochs define it, not the rule that chose them
    other_rule = sized | {"detector.sizing.min_epochs": "10", "detector.sizing.minutes": "15"}
    assert params["detector.sizing.min_epochs"] != "10"
    runs.insert(0, RunRecord("other_rule", "default", 4, other_rule, _metrics(75.0), QUICK))
    assert headline_table(runs, "adapt")[1] == {"headline": "other_rule"}


def _adapt_run(name: str, recipe: str, draw: int, base: str, metrics: dict, start: int = 5, **extra) -> RunRecord:
    params = _default_params() | {"experiment_name": "adapt", "adapt.recipe": recipe, "data.sources.pool.images": "50",
                                  "export.end_to_end.method": "deepword_then_logic", "adapt.base_run": base,
                                  "data.sources.pool.draw": str(draw)} | extra
    return RunRecord(name, name, start, params, metrics, QUICK)


def _draws(prefix: str, recipe: str, base: str) -> list[RunRecord]:
    return [_adapt_run(f"{prefix}{d}", recipe, d, base,
                       _metrics(70.0 + 10 * d) | {"eval.shift.detected.deepword_then_logic.hard.image_acc": 30.0 + d})
            for d in (0, 1)]


def test_the_headline_quotes_the_recommended_recipe_at_50_images_as_the_mean_of_its_draws():
    from stages.tables.headline import ADAPT_RECIPE

    assert ADAPT_RECIPE == "finetune_mixed"   # docs/adapt.md, "Which recipe"
    # its draws started from the headline's run; a newer run of another recipe, and the same recipe started from
    # another default run, are not quoted
    runs = [_adapt_run("mx", "mixed", 0, "base", _metrics(10.0), start=8),
            _adapt_run("other", "finetune_mixed", 0, "older", _metrics(20.0), start=7),
            *_draws("fm", "finetune_mixed", "base"),
            RunRecord("base", "default", 1, _default_params(), _metrics(80.0), QUICK)]
    table, sources = headline_table(runs, "adapt")
    assert sources["headline"] == "base" and sources["headline.adapt"] == "fm0,fm1"
    row = table.rows[-1]
    assert row[0] == "held-out domain, the default run trained further on SynWORD and 50 of its images (mean of 2 draws)"
    assert row[1:] == [65.0, 66.0, 67.0, 30.5]   # shift e2e of draws 60/70 (+i), image_acc 30/31


def test_a_default_run_newer_than_the_sweep_quotes_the_draws_of_the_run_they_started_from_and_says_so():
    """No draw started from the headline's run yet (a new commit's default run): the recommended recipe's draws that
    started from one default run, the newest draw's, are quoted, with a note naming that run."""
    runs = [RunRecord("base", "default", 3, _default_params(), _metrics(80.0), QUICK),
            *_draws("fm", "finetune_mixed", "older"),
            _adapt_run("stale", "finetune_mixed", 0, "oldest", _metrics(20.0), start=2),
            RunRecord("older", "default", 0, _default_params(), _metrics(70.0), {"git_commit": "1234567"} | QUICK)]
    table, sources = headline_table(runs, "adapt")
    assert sources["headline"] == "base" and sources["headline.adapt"] == "fm0,fm1"
    assert table.rows[-1][1:] == [65.0, 66.0, 67.0, 30.5]
    assert ("The last row's runs started from the default run default (1234567), not from the one above: `make adapt` "
            "has not run from it yet.") in table.notes


def test_a_mixed_headline_quotes_its_draws_whichever_default_run_they_name(monkeypatch):
    from stages.tables import headline

    monkeypatch.setattr(headline, "ADAPT_RECIPE", "mixed")
    # mixed trains from scratch: its draws count whichever default run they name as N=0
    runs = [_adapt_run("ft", "finetune", 0, "base", _metrics(10.0), start=7), *_draws("mx", "mixed", "older"),
            RunRecord("base", "default", 1, _default_params(), _metrics(80.0), QUICK)]
    table, sources = headline.headline_table(runs, "adapt")
    assert sources["headline"] == "base" and sources["headline.adapt"] == "mx0,mx1"
    assert table.rows[-1][0] == "held-out domain, trained on SynWORD and 50 of its images together (mean of 2 draws)"
    assert table.rows[-1][1:] == [65.0, 66.0, 67.0, 30.5]


def test_a_fine_tuning_headline_quotes_the_runs_started_from_the_headlines_run_alone(monkeypatch):
    from stages.tables import headline

    monkeypatch.setattr(headline, "ADAPT_RECIPE", "finetune")
    # newer, but a variant (a frozen backbone) and a fine-tuning of another default run: neither is quoted
    frozen = _adapt_run("frozen", "finetune", 0, "base", _metrics(10.0), start=7,
                        **{"init.detector_train.freeze": '["backbone"]'})
    other = _adapt_run("other", "finetune", 0, "old", _metrics(20.0), start=6)
    runs = [frozen, other, *_draws("ft", "finetune", "base"),
            RunRecord("base", "default", 1, _default_params(), _metrics(80.0), QUICK)]
    table, sources = headline.headline_table(runs, "adapt")
    assert sources["headline.adapt"] == "ft0,ft1"
    assert table.rows[-1][0].startswith("held-out domain after fine-tuning on 50 of its images (mean of 2 draws)")
    assert table.rows[-1][1:] == [65.0, 66.0, 67.0, 30.5]


def test_no_default_run_says_what_to_run_and_the_readme_markers_are_required(tmp_path):
    table, sources = headline_table([], "adapt")
    assert sources == {"headline": None} and not table.rows and "make pipeline" in table.notes[0]
    page = tmp_path / "README.md"
    page.write_text(f"# x\n\nbefore\n{HEADLINE_BEGIN}\nstale\n{HEADLINE_END}\nafter\n")
    write_headline(page, table)
    text = page.read_text()
    assert "stale" not in text and "make pipeline" in text and text.startswith("# x\n\nbefore\n")
    assert text.endswith(f"{HEADLINE_END}\nafter\n") and "## Headline" not in text
    page.write_text("no markers")
    with pytest.raises(SystemExit, match="no headline markers"):
        write_headline(page, table)


def test_a_store_without_adapt_runs_keeps_the_readmes_adapt_row(tmp_path):
    """``make compare`` on a store that has the default run but not the adapt sweep keeps the README's row of the
    recommended recipe (with a note), and a store that has the sweep writes its own."""
    from stages.tables.headline import keep_adapt_row

    base = RunRecord("base", "default", 1, _default_params(), _metrics(80.0), QUICK)
    with_sweep, _ = headline_table([*_draws("fm", "finetune_mixed", "base"), base], "adapt")
    page = tmp_path / "README.md"
    page.write_text(f"# x\n{HEADLINE_BEGIN}\nstale\n{HEADLINE_END}\n")
    write_headline(page, with_sweep)
    without, sources = headline_table([base], "adapt")
    assert "headline.adapt" not in sources and len(without.rows) == len(with_sweep.rows) - 1
    kept = keep_adapt_row(without, page)
    assert kept.rows == [*without.rows, with_sweep.rows[-1]]
    assert "kept from the README" in kept.notes[-2] and kept.notes[-1] == without.notes[-1]
