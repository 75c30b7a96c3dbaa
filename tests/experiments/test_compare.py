"""``make compare`` (``stages.tables``) on a store filled the way the engine fills it: parent runs whose params are the
flattened real config of each table row, plus runs that must be ignored (children, comparisons)."""

from __future__ import annotations

import csv
import shutil

import pytest

from deepword.paper import TABLE3_ACCURACY as PAPER_TABLE3
from pipeline.mlflow_ops import MlflowOps
from pipeline.tables import paired_difference
from pipeline.tracker import flatten_params
from stages.tables.compare import compare, main
from tests.experiments.pipeline_runs import compose_config
from tests.sqlite_store import fresh_store


def _parent(ops: MlflowOps, overrides: list[str], metrics: dict, name: str, params: dict | None = None) -> str:
    params = params or flatten_params(compose_config(overrides))
    run_id = ops.create_run(name, {"profile": "smoke", "seed": "42", "git_commit": "abc"})
    ops.log(run_id, metrics=metrics, params=params)
    ops.end(run_id)
    return run_id


def _eval(acc: float) -> dict:
    metrics = {"export.relation.ms_per_img_b1": 1.5, "relation.params": 12345.0}
    for method, base in (("deepword", acc), ("logic", acc - 20), ("logic_plus", acc - 1)):
        for i, s in enumerate(("easy", "hard", "mixed")):
            metrics[f"eval.gt.{method}.{s}.wheel_acc"] = base - i
            metrics[f"eval.gt.{method}.{s}.image_acc"] = base - 10 - i
    return metrics


@pytest.fixture(scope="module")
def filled_store(tmp_path_factory):
    """The store, filled once (composing each row's config takes seconds): tests get copies."""
    path = tmp_path_factory.mktemp("compare_store") / "mlflow.db"
    uri = fresh_store(path)
    ops = MlflowOps(uri, "deepword")
    ids = {
        "conv_fc": _parent(ops, ["experiment=table1", "relation/backbone=conv_fc"], _eval(80.0),
                           "smoke relation/backbone=conv_fc"),
        "resnet18": _parent(ops, ["experiment=table1", "relation/backbone=resnet18"], _eval(85.0),
                            "smoke relation/backbone=resnet18"),
        "neg0.1": _parent(ops, ["experiment=table2", "table2_row=neg0.1"], _eval(70.0), "smoke table2_row=neg0.1"),
        "default": _parent(ops, ["experiment=table3"], _eval(90.0), "smoke experiment=table3"),
    }
    # Newer, but not of the Table 2 sweep (another training budget): Table 2 keeps its sweep's run.
    ids["neg0.1_single"] = _parent(ops, ["table2_row=neg0.1"], _eval(60.0), "smoke table2_row=neg0.1")
    # Must be ignored: a newer -Sma run that stopped before evaluation, a child run carrying a row's
    # params, and a previous comparison run.
    _parent(ops, ["table2_row=small_mask"], {"relation.params": 1.0}, "smoke until relation")
    child = ops.create_run("relation", {"stage": "relation"}, parent_id=ids["resnet18"])
    ops.log(child, metrics=_eval(10.0),
            params=flatten_params(compose_config(["experiment=table1", "relation/backbone=resnet18"])))
    ops.end(child)
    # the datasets sweep: seeds 43 and 44 (44 twice: the newer run counts), and a seed-45 run that stopped
    # before evaluation (left out)
    datasets = flatten_params(compose_config(["experiment=datasets"]))
    for seed, acc in ((43, 90.0), (44, 50.0), (44, 97.0), (45, None)):
        ids[f"datasets.{seed}"] = _parent(ops, [], _eval(acc) if acc else {"relation.params": 1.0},
                                          f"smoke seed={seed}", params={**datasets, "seed": str(seed)})
    # a variant swept under its own name (`make datasets ARGS="experiment_name=rank2 ..."`): not in the
    # datasets table, only in its own
    ids["rank2.43"] = _parent(ops, [], _eval(80.0), "smoke seed=43 rank2",
                              params={**datasets, "seed": "43", "experiment_name": "rank2"})
    other = ops.create_run("comparison", {"kind": "comparison"})
    ops.log(other, metrics=_eval(5.0),
            params=flatten_params(compose_config(["experiment=table1", "relation/backbone=conv_fc"])))
    ops.end(other)
    return path, ids


@pytest.fixture()
def store(filled_store, tmp_path):
    """A copy of the filled store per test: ``compare`` logs its comparison run into it."""
    path, ids = filled_store
    shutil.copyfile(path, tmp_path / "mlflow.db")
    return f"sqlite:///{tmp_path / 'mlflow.db'}", ids


def _csv(path):
    with path.open() as f:
        return {row[0]: row for row in list(csv.reader(f))[1:]}


def test_tables_pick_each_rows_run_and_set_paper_numbers_beside_ours(store, tmp_path):
    uri, ids = store
    out = tmp_path / "cmp"
    result = compare(uri, "deepword", out)

    t1 = _csv(out / "table1.csv")
    assert float(t1["Conv+fc"][4]) == 78.0 and float(t1["ResNet-18"][4]) == 83.0  # mixed = base - 2
    assert t1["ResNet-18"][3] == ""  # paper latency unknown: left empty, shown n/a in markdown
    t2 = _csv(out / "table2.csv")
    assert float(t2["Neg0.1"][4]) == 68.0 and result["sources"]["table2.Neg0.1"] == ids["neg0.1"]
    assert float(t2["Conv+fc"][4]) == 78.0          # the Table 1 run serves Table 2's base row too
    assert t2["-Sma"][4] == "" and t2["56"][4] == ""  # no evaluated run of these configurations
    assert result["sources"]["table1.ResNet-18"] == ids["resnet18"]
    assert result["sources"]["table3"] == ids["default"]

    t3 = _csv(out / "table3.csv")
    assert [float(v) for v in t3["DeepWORD"][1:4]] == [90.0, 80.0, PAPER_TABLE3["deepword"]["easy"]]
    assert float(t3["Logic model"][9]) == PAPER_TABLE3["logic"]["mixed"] == 79.90
    md = (out / "table2.md").read_text()
    assert "| -Sma | n/a |" in md and "n/a" in (out / "table1.md").read_text()
    assert (out / "comparison.png").stat().st_size > 10_000

    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    logged = {a.path for a in client.list_artifacts(result["run_id"])}
    assert {"table1.md", "table2.csv", "table3.md", "comparison.md", "comparison.png"} <= logged
    assert client.get_run(result["run_id"]).data.tags["kind"] == "comparison"


def test_datasets_table_has_a_row_per_seed_the_mean_and_who_leads(store, tmp_path):
    uri, ids = store
    out = tmp_path / "cmp"
    result = compare(uri, "deepword", out, log=False)
    rows = _csv(out / "datasets.csv")
    assert list(rows) == ["43", "44", "mean of 2", "DeepWORD ahead / level / behind",
                          "DeepWORD - logic_plus (± s.e.)"]
    header = next(csv.reader((out / "datasets.csv").open()))
    hard_dw, hard_lp = header.index("hard wheel_acc DeepWORD"), header.index("hard wheel_acc logic_plus")
    assert float(rows["43"][hard_dw]) == 89.0 and float(rows["43"][hard_lp]) == 88.0  # hard = base - 1
    assert float(rows["44"][hard_dw]) == 96.0                                          # the newer seed-44 run
    assert float(rows["mean of 2"][hard_dw]) == 92.5
    assert rows["DeepWORD ahead / level / behind"][hard_dw] == "2/0/0"
    assert rows["DeepWORD - logic_plus (± s.e.)"][hard_dw] == "+1.00 ± 0.00"  # logic_plus = DeepWORD - 1
    assert result["sources"]["datasets.44"] == ids["datasets.44"] and "datasets.45" not in result["sources"]
    assert "| 43 | 89.00 | 88.00 |" in (out / "datasets.md").read_text()
    assert (out / "datasets.png").stat().st_size > 10_000
    assert "DeepWORD vs logic_plus over datasets" in (out / "comparison.md").read_text()


def test_datasets_table_of_a_variant_swept_under_its_own_name(store, tmp_path):
    uri, ids = store
    main(["--tracking-uri", uri, "--out", str(tmp_path / "v"), "--no-log", "--datasets", "rank2"])
    rows = _csv(tmp_path / "v" / "datasets.csv")
    assert list(rows) == ["43", "mean of 1", "DeepWORD ahead / level / behind", "DeepWORD - logic_plus (± s.e.)"]
    header = next(csv.reader((tmp_path / "v" / "datasets.csv").open()))
    assert float(rows["43"][header.index("hard wheel_acc DeepWORD")]) == 79.0
    assert "(rank2)" in (tmp_path / "v" / "datasets.md").read_text()


def test_a_table_reads_back_from_its_markdown():
    from pipeline.tables import Table, tables_in_markdown

    table = Table("Table 9: a title", ["Row", "N", "score", "note"],
                  [["seed 42", 50, 83.76, "+0.41 ± 0.12"], ["42", 0, None, "run x (abc, 2026-01-01)"]],
                  ["A note.", "Another: with a colon."])
    page = "# Results\n\nProse.\n\n" + table.markdown(level=3) + "\n### Not a table\n\nText.\n"
    assert tables_in_markdown(page) == {table.title: table}


def test_paired_difference_is_the_mean_with_its_standard_error():
    assert paired_difference([1.0, -1.0, 0.0, 2.0]) == "+0.50 ± 0.65"  # sd 1.29 / sqrt(4)
    assert paired_difference([-0.3]) == "-0.30" and paired_difference([]) == "n/a"


def test_profile_filter_and_missing_experiment(store, tmp_path, capsys):
    uri, _ = store
    result = compare(uri, "deepword", tmp_path / "none", profile="full", log=False)
    assert result["runs_considered"] == 0 and result["run_id"] is None
    assert "| DeepWORD | n/a | n/a | 99.17 |" in (tmp_path / "none" / "table3.md").read_text()
    assert "No rows: no evaluated run with experiment_name=datasets" in (tmp_path / "none" / "datasets.md").read_text()
    assert not (tmp_path / "none" / "datasets.png").exists()
    with pytest.raises(SystemExit, match="no MLflow experiment 'nope'"):
        main(["--tracking-uri", uri, "--experiment", "nope", "--out", str(tmp_path / "x")])


def test_results_page_gets_the_tables_and_charts_with_commit_and_date_and_keeps_the_rest(store, tmp_path):
    uri, _ = store
    page = tmp_path / "docs" / "results.md"
    page.parent.mkdir()
    page.write_text("# Results\n\nHistory written by hand.\n")
    for _ in range(2):  # a second run replaces the measured section instead of adding another
        compare(uri, "deepword", tmp_path / "cmp", log=False, results=page)
    text = page.read_text()
    assert text.startswith("# Results\n\nHistory written by hand.\n")
    assert text.count("Written by `make compare` on") == 1
    assert "### Table 3: logic model vs DeepWORD on easy / hard / mixed" in text
    assert "smoke experiment=table3 (abc, " in text  # the run's name, commit and date
    assert "![comparison.png](results/comparison.png)" in text
    assert (tmp_path / "docs" / "results" / "comparison.png").stat().st_size > 10_000


def test_bev_tables_take_the_newest_run_with_footprint_scores():
    from pipeline.runs import RunRecord
    from stages.tables.bev import bev_tables

    def run(name, metrics):
        return RunRecord(name, name, 0, {}, metrics, {})

    newest = {"bev.gt.deepword.all.ap": 86.3, "bev.gt.deepword.all.ate_m": 0.204, "bev.gt.deepword.paired.center_err_m": 0.15,
              "bev.shift.gt.deepword.all.aoe_deg": 42.3, "bev.gt.box_bottom.all.ap": 49.1,
              "bev.detected.deepword_then_logic.all.precision": 77.4,
              "bev.detected.deepword_then_logic.one_wheel.vehicles": 53.0,
              "bev.shift.detected.deepword_then_logic.one_wheel.ap": 4.2,
              "bev.detected.roles.acc": 90.8, "bev.detected.roles.relations": 740.0, "bev.shift.gt.roles.network_acc": 50.4}
    (main, populations, roles), used = bev_tables([run("no-bev", {"eval.gt.logic.mixed.wheel_acc": 90.0}), run("new", newest),
                                            run("old", {"bev.gt.deepword.all.ap": 9.0})])
    assert used == {"bev": "new"}
    rows = {tuple(r[:3]): r[3:] for r in main.rows}
    columns = [c for c in main.header[3:]]
    ground_truth = rows[("in domain", "ground truth", "DeepWORD")]
    assert ground_truth[columns.index("AP (%)")] == 86.3 and ground_truth[columns.index("ATE (m)")] == 0.204
    assert ground_truth[-1] == 0.15   # the paired median, as earlier runs reported it
    assert rows[("held out", "ground truth", "DeepWORD")][columns.index("AOE 360° (°)")] == 42.3
    assert rows[("in domain", "ground truth", "box bottom (no relation)")][0] == 49.1
    assert rows[("in domain", "detected", "`deepword_then_logic`")][columns.index("precision (%)")] == 77.4
    assert ("in domain", "ground truth", "`logic` (the paper's IoU rule)") not in rows   # nothing logged
    one_wheel = {r[0]: r[1:] for r in populations.rows}["one wheel"]
    assert one_wheel[populations.header[1:].index("vehicles in domain")] == 53   # a count, not 53.00
    assert one_wheel[populations.header[1:].index("AP (%) held out")] == 4.2
    assert "deepword_then_logic" in populations.title
    role_rows = {tuple(r[:3]): r[3:] for r in roles.rows}
    detected = role_rows[("in domain", "detected", "`deepword_then_logic`")]
    assert detected[0] == 740 and detected[1] == 90.8   # a count, then the share infer writes right
    assert role_rows[("held out", "ground truth", "`deepword`")][-1] == 50.4
    assert ("in domain", "ground truth", "`deepword`") not in role_rows   # nothing logged
    empty, none = bev_tables([])
    assert none == {"bev": None} and len(empty) == 1 and not empty[0].rows


def test_bev_tables_prefer_the_default_run_to_a_newer_variant():
    from pipeline.runs import RunRecord
    from pipeline.tracker import flatten_params
    from stages.tables.bev import bev_tables
    from tests.experiments.pipeline_runs import compose_config

    default = flatten_params(compose_config(["profile=smoke"]))
    needed = {"detector.shift.ap50.vehicle": 50.0, "eval.shift.gt.deepword.mixed.pair_f1": 60.0}

    def run(run_id, params, ap):
        return RunRecord(run_id, run_id, 0, params, needed | {"bev.gt.deepword.all.ap": ap}, {"profile": "smoke"})

    runs = [run("variant", default | {"detector.facing": "True"}, 90.0), run("default", default, 80.0)]
    assert bev_tables(runs)[1] == {"bev": "default"}
    assert bev_tables(runs[:1])[1] == {"bev": "variant"}     # no default run scored: the newest that is


def _logged_before_target(params: dict[str, str]) -> dict[str, str]:
    """A run's params as the engine logged them before relation/backbone named its class: ``relation.backbone.name``
    and every backbone's common fields (input_size, expansion, base_width: the quick profile's 16 on every one)."""
    params = dict(params)
    target = params.pop("relation.backbone._target_")
    params["relation.backbone.name"] = {"stages.relation.backbones.ConvFC": "conv_fc",
                                        "stages.relation.backbones.ResNet18": "resnet18"}[target]
    params.setdefault("relation.backbone.expansion", "1")
    params["relation.backbone.base_width"] = "16"
    return params


def test_runs_logged_before_the_backbone_named_its_class_match_their_own_row_only():
    from pipeline.runs import RunRecord
    from stages.tables.rows import TABLE1, RowMatcher

    matcher = RowMatcher()
    conv_fc, resnet18 = TABLE1
    for row, other in ((conv_fc, resnet18), (resnet18, conv_fc)):
        params = _logged_before_target(flatten_params(compose_config(list(row.overrides))))
        run = RunRecord("r", "old", 0, params, {}, {})
        assert matcher.matches(row, run) and not matcher.matches(other, run), row.label
    now = RunRecord("n", "new", 0, flatten_params(compose_config(list(resnet18.overrides))), {}, {})
    assert now.params["relation.backbone._target_"] == "stages.relation.backbones.ResNet18"
    assert matcher.matches(resnet18, now) and not matcher.matches(conv_fc, now)


def test_a_run_on_other_data_or_from_other_weights_is_no_table_row():
    """The adapt sweep's runs keep the default relation settings but train on other data (data=adapt) or start
    from the default run's weights (init=run): neither is Table 3's row."""
    from pipeline.runs import RunRecord
    from stages.tables.rows import TABLE3_ROW, RowMatcher

    matcher = RowMatcher()
    default = flatten_params(compose_config([]))
    assert matcher.matches(TABLE3_ROW, RunRecord("d", "default", 0, default, {}, {}))
    for changed in ({"data.name": "adapt"}, {"data.name": "word"}, {"init.source": "run"}):
        assert not matcher.matches(TABLE3_ROW, RunRecord("o", "other", 0, default | changed, {}, {})), changed
    before_init = {k: v for k, v in default.items() if not k.startswith("init.")}   # logged before the group existed
    assert matcher.matches(TABLE3_ROW, RunRecord("old", "old", 0, before_init, {}, {}))
