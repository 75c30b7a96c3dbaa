"""experiment=adapt (docs/adapt.md): the sweep and every job's configuration as the docs describe them, the adapt
table and curves of ``make compare`` from fake run records, and the lookup of the default run finetune starts from."""

from __future__ import annotations

import csv
import json
import math

import pytest
from omegaconf import OmegaConf

from pipeline.mlflow_ops import MlflowOps
from pipeline.runs import RunRecord
from pipeline.tracker import flatten_params
from stages.tables.adapt import BASE_LABEL, KEPT_RECIPES_NOTE, RECIPES, TITLE, adapt_chart, adapt_table
from stages.tables.adapt_base import main as base_main
from stages.tables.adapt_base import newest_default_run
from stages.tables.compare import compare
from tests.experiments.pipeline_runs import CONF, compose_config, hydra_config
from tests.sqlite_store import fresh_store

SAMPLES = {"n25_draw0": (25, 0), "n25_draw1": (25, 1), "n50_draw0": (50, 0), "n50_draw1": (50, 1),
           "n100_draw0": (100, 0), "n200_draw0": (200, 0), "n400_draw0": (400, 0)}
BY_NAME = {"n100_draw1": (100, 1), "n200_draw1": (200, 1)}   # second draws outside the sweep, run by name
OWN_DOMAIN = {"n1050_draw0": (1050, 0)}   # scratch with the default run's budget, outside the sweep, run by name




def _job(recipe: str, sample: str, *more: str) -> dict:
    return compose_config(["experiment=adapt", f"adapt_recipe={recipe}", f"adapt_sample={sample}",
                           "adapt.base_run=base0", *more])


def test_the_sweep_runs_four_recipes_on_seven_samples_two_jobs_at_a_time():
    hydra = hydra_config(["experiment=adapt"])
    assert hydra.mode.name == "MULTIRUN" and hydra.launcher.n_jobs == 2
    params = dict(hydra.sweeper.params)
    assert params["adapt_recipe"].split(",") == ["finetune", "finetune_mixed", "scratch", "mixed"]
    assert sorted(p.stem for p in (CONF / "adapt_recipe").glob("*.yaml")) == sorted(params["adapt_recipe"].split(","))
    assert params["adapt_sample"].split(",") == list(SAMPLES)            # two draws where N <= 50
    assert sorted(p.stem for p in (CONF / "adapt_sample").glob("*.yaml")) == sorted({**SAMPLES, **BY_NAME, **OWN_DOMAIN})
    assert hydra.callbacks.sweep_summary._target_ == "pipeline.sweep.SweepSummary"


def _steps(budget: dict, n: int) -> tuple[int, int]:
    """Optimizer steps of a budget row at the quick profile's batch sizes (conf/adapt_budget/default.yaml's table):
    detector 8 (last part-batch dropped), relation 16 with each image twice, ~80 % of N in train."""
    train = round(0.8 * n) - (2 if n == 25 else 0)   # N=25: 2 of its ~7 frames are val (~7 images)
    return budget["detector_epochs"] * (train // 8), budget["relation_epochs"] * math.ceil(2 * train / 16)


@pytest.mark.parametrize("sample", list({**SAMPLES, **BY_NAME}))
def test_scratch_and_mixed_jobs_are_what_the_docs_say(sample):
    n, draw = {**SAMPLES, **BY_NAME}[sample]
    default = compose_config([])
    scratch, mixed = _job("scratch", sample), _job("mixed", sample)
    for job, recipe in ((scratch, "scratch"), (mixed, "mixed")):
        pool = job["data"]["sources"]["pool"]
        assert job["experiment_name"] == "adapt" and job["adapt"]["recipe"] == recipe
        assert (pool["images"], pool["draw"], job["adapt"]["size"]) == (n, draw, f"n{n}")
        assert pool["generator"] == job["shift"]["data"]                 # the held-out test set's families and sizes
        assert pool["stream"] not in (job["shift"]["data"]["stream"], job["data"]["sources"]["synword"]["stream"])
        assert pool["use"] == {"train": "train", "val": "val", "test": None}   # val: the N images' own
        assert job["data"]["sources"]["synword"]["frames"] == default["data"]["frames"]
        assert job["init"]["source"] == "scratch" and job["pipeline"]["skip"] == ["facing", "bev"]   # shift_data stays
        assert job["trainer"]["threads"] == 1 and job["relation"]["train"]["threads"] == 1
        assert job["relation"]["train"]["seed"] == default["relation"]["train"]["seed"]
    assert scratch["data"]["sources"]["synword"]["use"] == {"train": None, "val": None, "test": "test",
                                                            "val_prior": "val"}
    budget = scratch["adapt"]["budget"]["scratch"][f"n{n}"]
    assert scratch["detector"]["epochs"] == budget["detector_epochs"] != default["detector"]["epochs"]
    assert scratch["detector"]["val_every_n_epochs"] == budget["detector_val_every"]
    assert (scratch["relation"]["train"]["epochs"], scratch["relation"]["train"]["patience"]) == \
        (budget["relation_epochs"], budget["relation_patience"])
    det_steps, rel_steps = _steps(budget, n)
    assert 2800 <= det_steps <= 3300 and 1500 <= rel_steps <= 1700       # the steps the budget's comment names
    # mixed: the generator's train split beside the new images, the profile's budget, the pool's val alone
    # ... and the generator's val split only as the operating point's prior (docs/detector.md), weighed as 40 images
    assert mixed["data"]["sources"]["synword"]["use"] == {"train": "train", "val": None, "test": "test",
                                                          "val_prior": "val"}
    assert mixed["export"]["operating_point"]["prior_images"] == 40
    assert mixed["data"]["sources"]["pool"]["train_share"] == 0.25
    assert mixed["detector"] == {**default["detector"]}
    assert {k: v for k, v in mixed["relation"].items() if k != "train"} == \
        {k: v for k, v in default["relation"].items() if k != "train"}
    assert mixed["relation"]["train"]["epochs"] == default["relation"]["train"]["epochs"]
    # finetune and scratch at one N and draw share the dataset (one data and priors entry in the cache)
    assert scratch["data"] == _job("finetune", sample)["data"]


@pytest.mark.parametrize("sample", ["n25_draw1", "n400_draw0"])
def test_finetune_jobs_start_from_the_base_run_with_a_budget_in_steps(sample):
    n, _ = SAMPLES[sample]
    job = _job("finetune", sample)
    assert job["adapt"]["recipe"] == "finetune" and job["init"]["source"] == "run" and job["init"]["run"] == "base0"
    budget = job["adapt"]["budget"]["finetune"][f"n{n}"]
    assert job["init"]["detector_train"]["epochs"] == budget["detector_epochs"]
    assert job["init"]["relation_train"]["epochs"] == budget["relation_epochs"]
    assert job["init"]["relation_train"]["patience"] == budget["relation_patience"]
    assert job["detector"]["val_every_n_epochs"] == budget["detector_val_every"]
    assert job["data"]["sources"]["synword"]["use"] == {"train": None, "val": None, "test": "test", "val_prior": "val"}
    det_steps, rel_steps = _steps(budget, n)
    assert 550 <= det_steps <= 650 and 300 <= rel_steps <= 340


@pytest.mark.parametrize("sample", ["n25_draw0", "n400_draw0"])
def test_finetune_mixed_jobs_start_from_the_base_run_and_replay_the_generators_train_split(sample):
    n, _ = SAMPLES[sample]
    job, mixed = _job("finetune_mixed", sample), _job("mixed", sample)
    assert job["adapt"]["recipe"] == "finetune_mixed" and job["init"]["source"] == "run"
    assert job["init"]["run"] == "base0" and job["data"] == mixed["data"]   # mixed's dataset: one cache entry
    budget = job["adapt"]["budget"]["finetune_mixed"]
    assert job["init"]["detector_train"]["epochs"] == budget["detector_epochs"]
    assert (job["init"]["relation_train"]["epochs"], job["init"]["relation_train"]["patience"]) == \
        (budget["relation_epochs"], budget["relation_patience"])
    assert job["init"]["relation_train"]["select"] == "loss"
    assert job["detector"]["val_every_n_epochs"] == budget["detector_val_every"]
    # the default run's own budget at every N (its epochs over the generator's ~840 train images and the new ones
    # repeated to a quarter of the split, ~1,050-1,150 images): the quick profile's most detector epochs
    quick = OmegaConf.load(CONF / "profile/quick.yaml")
    assert budget["detector_epochs"] == quick.detector.sizing.max_epochs
    train = 840 / 0.75
    assert 7000 <= budget["detector_epochs"] * (train // 8) <= 8000
    assert 4000 <= budget["relation_epochs"] * math.ceil(2 * train / 16) <= 4500


def test_the_guides_command_trains_what_the_sweep_measured_as_finetune_mixed():
    """docs/your_camera.md's recipe, `data=mixed init=run init.budget=whole`, fills in the budget the sweep's
    finetune_mixed jobs give outright: the same epochs, patience, learning rate and weight average for both networks
    (the data config names no image count, so the quick profile's sized epochs are its most)."""
    from stages.detector.warm_start import budget as detector_budget
    from stages.relation.warm_start import budget as relation_budget

    quick = OmegaConf.load(CONF / "profile/quick.yaml")
    guide = OmegaConf.create(compose_config(["data=mixed", "data.sources.yours.root=/nowhere", "init=run",
                                             "init.run=base0", "init.budget=whole",
                                             f"detector.epochs={quick.detector.sizing.max_epochs}"]))
    job = OmegaConf.create(_job("finetune_mixed", "n50_draw0", f"detector.epochs={quick.detector.sizing.max_epochs}"))
    for budget, net in ((detector_budget, "detector"), (relation_budget, "relation")):
        assert budget(dict(guide.init[f"{net}_train"]), guide) == budget(dict(job.init[f"{net}_train"]), job)
    assert guide.detector.val_every_n_epochs == job.detector.val_every_n_epochs


def test_the_held_out_domains_own_default_run_is_scratch_on_as_many_images_with_the_default_runs_budget():
    (sample, (n, draw)), = OWN_DOMAIN.items()
    job, default = _job("scratch", sample), compose_config([])
    pool = job["data"]["sources"]["pool"]
    assert (pool["images"], pool["draw"], job["adapt"]["size"]) == (n, draw, f"n{n}")
    sizing = default["detector"]["sizing"]
    assert job["detector"]["epochs"] == sizing["max_epochs"]
    assert job["detector"]["val_every_n_epochs"] == default["detector"]["val_every_n_epochs"]
    assert (job["relation"]["train"]["epochs"], job["relation"]["train"]["patience"]) == \
        (default["relation"]["train"]["epochs"], default["relation"]["train"]["patience"])


def test_finetune_without_a_base_run_does_not_compose():
    from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue

    with pytest.raises((MissingMandatoryValue, InterpolationToMissingValueError), match="adapt.base_run"):
        compose_config(["experiment=adapt", "adapt_recipe=finetune"])


def test_smoke_budget_trains_one_epoch_of_everything():
    job = _job("scratch", "n400_draw0", "profile=smoke", "adapt_budget=smoke")
    assert job["detector"]["epochs"] == 1 and job["relation"]["train"]["epochs"] == 1
    assert job["data"]["sources"]["synword"]["frames"] == compose_config(["profile=smoke"])["data"]["frames"]
    assert job["data"]["sources"]["pool"]["generator"]["image_size"] == [320, 240]


# --- make compare: the adapt table and curves ---------------------------------------------------------------

def _figures(e2e: float, ap: float, method: str = "deepword_then_logic") -> dict[str, float]:
    return {f"eval.shift.detected.{method}.mixed.pair_f1": e2e, "eval.shift.gt.deepword.mixed.pair_f1": e2e + 10,
            "detector.shift.ap50.vehicle": ap, "detector.shift.ap50.wheel": ap - 5,
            f"eval.detected.{method}.mixed.pair_f1": 90.0}


def _run(run_id: str, recipe: str | None, n: int | None, draw: int, metrics: dict, experiment="adapt",
         base="base0", method="deepword_then_logic") -> RunRecord:
    params = {"export.end_to_end.method": method, "adapt.base_run": json.dumps(base) if base is None else base}
    if experiment:
        params["experiment_name"] = experiment
    if recipe:
        params |= {"adapt.recipe": recipe, "data.sources.pool.images": str(n), "data.sources.pool.draw": str(draw)}
    return RunRecord(run_id, f"smoke {recipe} n{n} d{draw}", 0, params, metrics, {"git_commit": "abc"})


def _runs() -> list[RunRecord]:
    """Newest first, as load_runs gives them."""
    return [
        _run("ft25d0", "finetune", 25, 0, _figures(60.0, 70.0)),
        _run("ft25d1", "finetune", 25, 1, _figures(50.0, 60.0)),
        _run("ft25d1_old", "finetune", 25, 1, _figures(10.0, 10.0)),            # older: the newer one counts
        _run("ft100", "finetune", 100, 0, _figures(70.0, 80.0, "deepword"), method="deepword"),
        _run("sc25", "scratch", 25, 0, _figures(20.0, 30.0)),
        _run("sc100_unfinished", "scratch", 100, 0, {"detector.shift.ap50.vehicle": 5.0}),   # no evaluate: left out
        _run("mix25", "mixed", 25, 0, _figures(55.0, 65.0)),
        _run("other_sweep", "scratch", 400, 0, _figures(99.0, 99.0), experiment="mine"),
        _run("base0", None, None, 0, _figures(40.0, 50.0), experiment=None, base=None),
    ]


def test_adapt_table_has_mean_and_range_over_draws_and_the_default_run_at_n0():
    table, used = adapt_table(_runs())
    col = {name: i for i, name in enumerate(table.header)}
    rows = {(r[0], r[1]): r for r in table.rows}
    assert list(rows) == [(BASE_LABEL, 0), (RECIPES["finetune"], 25), (RECIPES["finetune"], 100),
                          (RECIPES["scratch"], 25), (RECIPES["mixed"], 25)]
    ft25 = rows[(RECIPES["finetune"], 25)]
    assert ft25[col["draws"]] == 2
    assert (ft25[col["e2e mean"]], ft25[col["e2e min"]], ft25[col["e2e max"]]) == (55.0, 50.0, 60.0)
    assert (ft25[col["ap50.wheel mean"]], ft25[col["ap50.wheel min"]]) == (60.0, 55.0)
    assert ft25[col["gt mean"]] == 65.0 and ft25[col["in-domain e2e mean"]] == 90.0
    assert rows[(RECIPES["finetune"], 100)][col["e2e mean"]] == 70.0   # the run's own end-to-end method
    assert rows[(BASE_LABEL, 0)][col["e2e mean"]] == 40.0 and used["adapt.base"] == "base0"
    assert used["adapt.finetune.25.1"] == "ft25d1" and "adapt.scratch.100.0" not in used
    assert not any(k.startswith("adapt.scratch.400") for k in used)     # another sweep's name
    mine, used_mine = adapt_table(_runs(), "mine")
    assert [r[1] for r in mine.rows] == [0, 400] and "The sweep's runs: experiment_name=mine." in mine.notes
    assert mine.title == table.title   # its job names base0 too; one title, so the page's table is found again
    assert any("No N=0 row: the base run base0 is not among" in n for n in adapt_table(_runs()[:-1])[0].notes)
    empty, none = adapt_table([])
    assert not empty.rows and not none and any("make adapt" in n for n in empty.notes)


def test_a_frozen_variant_is_its_own_row_and_a_curve_keeps_one_default_run():
    frozen = _run("ft25_frozen", "finetune", 25, 0, _figures(5.0, 5.0))
    frozen.params["init.detector_train.freeze"] = '["backbone"]'
    other_base = _run("ft25_other_base", "finetune", 25, 0, _figures(1.0, 1.0), base="base9")
    table, used = adapt_table([frozen, other_base, *_runs()])
    rows = {(r[0], r[1]): r for r in table.rows}
    assert ("finetune (backbone frozen)", 25) in rows and used["adapt.finetune (backbone frozen).25.0"] == "ft25_frozen"
    assert used["adapt.finetune.25.0"] == "ft25d0", "newer, but started from another default run: not on the curve"


def test_adapt_chart_draws_the_curves(tmp_path):
    table, _ = adapt_table(_runs())
    adapt_chart(table, tmp_path / "adapt.png")
    assert (tmp_path / "adapt.png").stat().st_size > 20_000


def _store(path, runs) -> str:
    """A sqlite MLflow store holding ``runs`` (newest first), each finetune job naming the store's id of the oldest
    run (the base run) as its ``adapt.base_run``; its URI."""
    uri = fresh_store(path)
    ops = MlflowOps(uri, "deepword")
    base_id = None
    for run in reversed(runs):
        run_id = ops.create_run(run.name, {"profile": "smoke", "git_commit": "abc"})
        ops.log(run_id, metrics=run.metrics, params=run.params | ({"adapt.base_run": base_id} if base_id else {}))
        ops.end(run_id)
        base_id = base_id or run_id
    return uri


def test_compare_writes_the_adapt_table_curves_and_results_section(tmp_path):
    uri = _store(tmp_path / "mlflow.db", _runs())
    page = tmp_path / "results.md"
    result = compare(uri, "deepword", tmp_path / "cmp", log=False, results=page)
    with (tmp_path / "cmp" / "adapt.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0][:4] == ["Recipe", "N images", "draws", "e2e mean"] and len(rows) == 6
    assert rows[1][0] == BASE_LABEL and float(rows[1][3]) == 40.0    # N=0: the base run, found by its id
    assert (tmp_path / "cmp" / "adapt.png").stat().st_size > 20_000
    assert "How many images to label" in (tmp_path / "cmp" / "adapt.md").read_text()
    assert "![adapt.png](results/adapt.png)" in page.read_text()
    assert sum(k.startswith("adapt.") for k in result["sources"]) == 6



def test_a_store_without_the_sweeps_runs_keeps_the_pages_adapt_table(tmp_path):
    """The sweep ran against another store: ``make compare`` on one that has the default run alone keeps the page's
    adapt table and curves (with a note saying so) instead of writing an empty table over them."""
    from stages.tables.compare import KEPT_NOTE, measured_tables

    page = tmp_path / "results.md"
    compare(_store(tmp_path / "sweep.db", _runs()), "deepword", tmp_path / "cmp", log=False, results=page)
    title = next(t for t in measured_tables(page) if t.startswith("How many images to label"))
    measured = measured_tables(page)[title]
    assert len(measured.rows) == 5 and KEPT_NOTE not in measured.notes
    compare(_store(tmp_path / "base.db", _runs()[-1:]), "deepword", tmp_path / "again", log=False, results=page)
    kept = measured_tables(page)[title]
    assert (kept.header, kept.rows, kept.notes) == (measured.header, measured.rows, [*measured.notes, KEPT_NOTE])
    assert (tmp_path / "again" / "adapt.png").stat().st_size > 20_000
    compare(_store(tmp_path / "base2.db", _runs()[-1:]), "deepword", tmp_path / "third", log=False, results=page)
    assert page.read_text().count(KEPT_NOTE) == 1   # kept again, noted once


def test_a_sweep_of_one_recipe_adds_its_curve_and_keeps_the_pages_other_recipes(tmp_path):
    """The page's adapt table came from a sweep of every recipe; a store that holds one recipe's runs under another
    experiment name replaces that recipe's rows, keeps the others' (and the N=0 row) with a note naming them, and
    draws them all; run again, nothing is kept twice."""
    from stages.tables.compare import measured_tables

    page = tmp_path / "results.md"
    compare(_store(tmp_path / "sweep.db", _runs()), "deepword", tmp_path / "cmp", log=False, results=page)
    before = measured_tables(page)[TITLE]
    finetune_again = [_run(f"ftmix{n}", "finetune_mixed", n, 0, _figures(80.0, 90.0), experiment="whole")
                      for n in (25, 50)]
    for _ in range(2):
        compare(_store(tmp_path / "one.db", [*finetune_again, _runs()[-1]]), "deepword", tmp_path / "again",
                log=False, results=page, adapt_experiment="whole")
        after = measured_tables(page)[TITLE]
        labels = [(r[0], r[1]) for r in after.rows]
        assert labels == [(BASE_LABEL, 0), (RECIPES["finetune"], 25), (RECIPES["finetune"], 100),
                          (RECIPES["finetune_mixed"], 25), (RECIPES["finetune_mixed"], 50), (RECIPES["scratch"], 25),
                          (RECIPES["mixed"], 25)]
        assert [r for r in after.rows if r[0] == RECIPES["mixed"]] == [r for r in before.rows
                                                                      if r[0] == RECIPES["mixed"]]
        kept = [n for n in after.notes if n.startswith("Rows of")]
        assert kept == [KEPT_RECIPES_NOTE.format(recipes=f"`{RECIPES['finetune']}`, `{RECIPES['scratch']}`, "
                                                         f"`{RECIPES['mixed']}`")]
        assert "The sweep's runs: experiment_name=whole." in after.notes
    assert (tmp_path / "again" / "adapt.png").stat().st_size > 20_000


# --- the default run finetune starts from --------------------------------------------------------------------

def test_the_base_run_is_the_newest_finished_default_run_of_the_profile(tmp_path, capsys):
    default = flatten_params(compose_config(["profile=smoke"]))
    metrics = {"detector.shift.ap50.vehicle": 50.0, "eval.shift.gt.deepword.mixed.pair_f1": 60.0}

    def run(run_id, params, tags=None, m=metrics):
        return RunRecord(run_id, run_id, 0, params, m, {"profile": "smoke"} | (tags or {}))

    adapt_job = flatten_params(_job("scratch", "n25_draw0", "profile=smoke"))
    runs = [run("sweep_job", adapt_job), run("other_profile", default, {"profile": "quick"}),
            run("ablated", default | {"relation.model.gat": "false"}), run("unevaluated", default, m={}),
            run("warm", default | {"init.source": "run"}), run("plain", default), run("older", default)]
    assert newest_default_run(runs, "smoke").run_id == "plain"
    assert newest_default_run(runs[:-2], "smoke") is None
    uri = fresh_store(tmp_path / "mlflow.db")
    with pytest.raises(SystemExit, match=r"no finished default run \(profile smoke.*run `make pipeline` first"):
        base_main(["--tracking-uri", uri, "--profile", "smoke"])
