"""The paper tables as Hydra sweeps: what each experiment sweeps, the parallel launcher, the Table 2 rows'
resolved relation settings, and a real two-job sweep whose summary shows the shared stages computed once."""

from __future__ import annotations

import json

import pytest

from pipeline.runs import RunRecord
from pipeline.sweep import format_table, read_jobs, stage_totals, summarize
from pipeline.tracker import flatten_params
from stages.tables.rows import TABLE1, TABLE2, TABLE3_ROW, RowMatcher
from tests.experiments.pipeline_runs import CONF, compose_config, hydra_config, run_pipeline


@pytest.mark.parametrize(("table", "axis", "values"), [
    ("table1", "relation/backbone", "conv_fc,resnet18"),
    ("table2", "table2_row", "conv_fc,neg0.1,fewer_neg,small_mask,input56,ex4"),
])
def test_experiments_sweep_the_paper_rows_with_two_parallel_jobs(table, axis, values):
    hydra = hydra_config([f"experiment={table}"])
    assert hydra.mode.name == "MULTIRUN"
    assert dict(hydra.sweeper.params) == {axis: values}
    assert hydra.launcher._target_.endswith("JoblibLauncher") and hydra.launcher.n_jobs == 2
    assert hydra.callbacks.sweep_summary._target_ == "pipeline.sweep.SweepSummary"


def test_datasets_experiment_runs_the_default_configuration_on_ten_root_seeds():
    hydra = hydra_config(["experiment=datasets"])
    assert hydra.mode.name == "MULTIRUN" and dict(hydra.sweeper.params) == {"seed": "42,43,44,45,46,47,48,49,50,51"}
    assert hydra.launcher.n_jobs == 2
    ours, default = compose_config(["experiment=datasets"]), compose_config([])
    assert ours["relation"]["train"].pop("threads") == 1
    default["relation"]["train"].pop("threads")
    assert ours["relation"] == default["relation"] and ours["eval"] == default["eval"]
    assert ours["pipeline"]["skip"] == ["detector", "facing", "bev"]


def test_table3_is_one_job_of_the_default_configuration():
    hydra = hydra_config(["experiment=table3"])
    assert hydra.mode.name == "MULTIRUN" and not hydra.sweeper.params
    assert compose_config(["experiment=table3"])["relation"] == compose_config([])["relation"]


@pytest.mark.parametrize("table", ["table1", "table2", "table3"])
def test_paper_tables_leave_the_detector_out_and_keep_every_stage_their_numbers_come_from(table):
    from omegaconf import OmegaConf

    from pipeline.dag import load_stages, select_stages

    cfg = OmegaConf.create(compose_config([f"experiment={table}"]))
    selected, left_out = select_stages(load_stages(cfg), None, list(cfg.pipeline.skip))
    assert left_out == {"detector": "pipeline.skip", "facing": "pipeline.skip", "bev": "pipeline.skip"}
    assert selected == ["data", "shift_data", "priors", "relation", "export", "evaluate"]  # held-out rows too


def _without_sweep_fields(train: dict) -> dict:
    """relation.train less what the ablation sweeps set for their rows (budget and threads)."""
    return {k: v for k, v in train.items() if k not in ("epochs", "patience", "threads")}


@pytest.mark.parametrize("profile", ["smoke", "quick", "full"])
def test_ablation_sweeps_train_every_row_with_the_profiles_sweep_budget(profile):
    pipeline_run = compose_config([f"profile={profile}"])
    budget = pipeline_run["sweep"]
    for overrides in (["experiment=table1", "relation/backbone=conv_fc"], ["experiment=table1", "relation/backbone=resnet18"],
                      ["experiment=table2", "table2_row=small_mask"], ["experiment=table2", "table2_row=ex4"]):
        row = compose_config([*overrides, f"profile={profile}"])
        train = row["relation"]["train"]
        assert (train["epochs"], train["patience"]) == (budget["relation_epochs"], budget["relation_patience"])
        assert train["threads"] == 1  # two rows side by side on two cores, not four threads on two
        assert row["trainer"] == pipeline_run["trainer"]
        assert _without_sweep_fields(train) == _without_sweep_fields(pipeline_run["relation"]["train"])
    assert pipeline_run["relation"]["train"]["threads"] == 1  # beside the facing stage (pipeline.cores)
    if profile == "quick":  # the point of the budget: the sweeps' rows train shorter than the pipeline's
        assert budget["relation_epochs"] < pipeline_run["relation"]["train"]["epochs"]


def test_table1_compares_both_backbones_on_the_same_crops():
    sizes = {b: compose_config(["experiment=table1", f"relation/backbone={b}"])["relation"]["backbone"]["input_size"]
             for b in ("conv_fc", "resnet18")}
    assert sizes == {"conv_fc": 28, "resnet18": 28}


def test_each_table_row_is_the_configuration_compare_reads_as_that_row():
    matcher = RowMatcher()
    rows = [*TABLE1, *TABLE2[1:], TABLE3_ROW]  # Table 2's Conv+fc row is Table 1's
    names = ["conv_fc", "neg0.1", "fewer_neg", "small_mask", "input56", "ex4"]
    swept = {TABLE1[0]: ["experiment=table1", "relation/backbone=conv_fc"],
             TABLE1[1]: ["experiment=table1", "relation/backbone=resnet18"], TABLE3_ROW: ["experiment=table3"]}
    swept |= {row: ["experiment=table2", f"table2_row={name}"] for name, row in zip(names, TABLE2, strict=True)}
    for row, overrides in swept.items():
        run = RunRecord("id", "name", 0, flatten_params(compose_config(overrides)), {}, {})
        expected = [TABLE1[0].label] if row == TABLE2[0] else [row.label]
        # Table 2's 56_ex_4 row is the default network alone; Table 3's row ships the default ensemble of three
        # (relation.ensemble), another model, so neither run is the other row
        assert [r.label for r in rows if matcher.matches(r, run)] == expected, overrides


def test_an_ablated_run_is_never_the_default_row():
    """Every ablation changes a relation field; none of them may fill the default Table 3 row. (ex4 and input56
    ablate the Conv+fc network towards the default backbone, conv_fc_56_ex4: on it they change nothing.)"""
    same_as_default = {"none", "ex4", "input56"}
    matcher = RowMatcher()
    for ablation in sorted(p.stem for p in (CONF / "ablation").glob("*.yaml")):
        run = RunRecord("id", "name", 0, flatten_params(compose_config([f"ablation={ablation}"])), {}, {})
        assert matcher.matches(TABLE3_ROW, run) == (ablation in same_as_default), ablation


def test_a_run_trained_otherwise_is_not_the_default_row_but_a_shorter_one_is():
    matcher = RowMatcher()

    def matches(overrides: list[str]) -> bool:
        return matcher.matches(TABLE3_ROW, RunRecord("id", "name", 0, flatten_params(compose_config(overrides)), {}, {}))

    assert matches(["relation.train.epochs=5", "relation.train.patience=2", "relation.train.threads=1", "seed=43"])
    assert not matches(["relation.train.detection_noise.copies=0"])   # trained on labels only
    assert not matches(["relation.train.lr=0.01"])


def _job(tmp_path, num: int, overrides: list[str], hits: dict[str, bool]):
    job = tmp_path / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    stages = {name: {"hit": hit, "key": f"{name}-key" if name != "relation" else f"rel-{num}", "reason": "",
                     "seconds": 1.0, "metrics": {}} for name, hit in hits.items()}
    (job / "summary.json").write_text(json.dumps({"mlflow_run_id": f"run{num}", "pipeline_seconds": 2.5,
                                                  "stages": stages}))


def test_sweep_summary_counts_computed_and_reused_entries(tmp_path, capsys):
    _job(tmp_path, 0, ["relation/backbone=conv_fc", "profile=smoke"], {"data": False, "priors": True, "relation": False})
    _job(tmp_path, 1, ["relation/backbone=resnet18", "profile=smoke"], {"data": True, "priors": False, "relation": False})
    summary = summarize(tmp_path)
    assert summary["stages"]["data"] == {"jobs": 2, "distinct_keys": 1, "computed": 1, "reused": 1}
    assert summary["stages"]["relation"] == {"jobs": 2, "distinct_keys": 2, "computed": 2, "reused": 0}
    assert json.loads((tmp_path / "sweep_summary.json").read_text())["jobs"][1]["job"] == "1"
    out = capsys.readouterr().out
    assert "1  relation/backbone=resnet18" in out and "profile=smoke" not in out.splitlines()[2]
    table = format_table(read_jobs(tmp_path), stage_totals(read_jobs(tmp_path)))
    assert table.splitlines()[-1].split()[-3:] == ["1/2", "1/2", "2/2"]


@pytest.mark.slow
@pytest.mark.parametrize("launcher", [
    "local_parallel",   # joblib: the jobs are worker processes of the launching one
    "submitit_local",   # submitit's local executor: each job a process of its own, as on SLURM nodes
])
def test_parallel_sweep_computes_shared_stages_once(tmp_path, launcher):
    proc = run_pipeline(tmp_path, ["experiment=table1", "profile=smoke", "data.frames=4", "data.workers=2", "pipeline.until=priors",
                                   f"hydra/launcher={launcher}"],
                        f"sqlite:///{tmp_path / 'mlflow.db'}")
    summary = json.loads((tmp_path / "sweep" / "sweep_summary.json").read_text())
    assert len(summary["jobs"]) == 2
    if launcher == "submitit_local":  # the jobs really went through submitit: its job folders and results
        assert len(list((tmp_path / "sweep" / ".submitit").glob("*/*_result.pkl"))) == 2
    for stage in ("data", "priors"):
        assert summary["stages"][stage] == {"jobs": 2, "distinct_keys": 1, "computed": 1, "reused": 1}
    assert "computed / jobs" in proc.stdout

    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("deepword").experiment_id])
    names = sorted(r.info.run_name for r in runs if "mlflow.parentRunId" not in r.data.tags)
    assert [n.split()[:2] for n in names] == [["smoke", "relation/backbone=conv_fc"],
                                              ["smoke", "relation/backbone=resnet18"]]
