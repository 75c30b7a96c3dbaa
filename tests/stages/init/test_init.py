"""The ``init`` group: starting the detector and the relation network from an earlier run's weights
(stages/training/init_source.py, docs/stages.md "init"). Plan-time checks run on hand-made weights; one tiny smoke
pipeline (data, priors, relation, detector) is the parent of the runs that start from it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pipeline.dag import load_stages
from pipeline.errors import PipelineError
from pipeline.keys import PlanContext, key_parts
from stages.training.init_source import INIT_INPUT

REPO = Path(__file__).resolve().parents[3]
# The smoke profile shrunk further (tests/experiments/pipeline_runs.TINY), export and what needs it left out.
TINY = ["profile=smoke", "relation.train.limit_train_images=12", "relation.train.limit_val_images=8",
        "detector.limit_train_batches=2", "detector.limit_val_batches=1", "trainer.threads=1",
        "pipeline.skip=[export,shift_data]"]


def compose_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=[*TINY, *overrides])


def stage_parts(cfg, stage: str, context: PlanContext | None = None):
    """The key parts of ``stage`` (and of everything upstream of it, for its input keys)."""
    keys, parts = {}, None
    for name, spec in load_stages(cfg).items():
        parts = key_parts(spec, cfg, keys, context)
        keys[name] = parts.key
        if name == stage:
            return parts
    raise AssertionError(stage)


def tiny_detector_weights(path: Path, cfg, scale: float = 1.0) -> Path:
    from stages.detector.model import build_centernet, model_config

    torch.manual_seed(0)
    net = build_centernet(model_config(OmegaConf.to_container(cfg.detector, resolve=True)))
    state = {k: v * scale if v.is_floating_point() else v for k, v in net.state_dict().items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)
    return path


def test_scratch_adds_nothing_to_the_keys():
    """init=scratch: the training stages' keys are those of a config without the group at all."""
    cfg = compose_cfg()
    assert cfg.init.source == "scratch"
    bare = compose_cfg()
    with open_dict_of(bare):
        del bare["init"]
    for stage in ("relation", "detector"):
        with_group, without = stage_parts(cfg, stage), stage_parts(bare, stage)
        assert with_group.key == without.key
        assert "init" not in with_group.config and INIT_INPUT not in with_group.inputs and not with_group.tags


def open_dict_of(cfg):
    from omegaconf import open_dict

    return open_dict(cfg)


def test_checkpoints_key_covers_content_and_budget(tmp_path):
    weights = tiny_detector_weights(tmp_path / "a" / "model.pt", compose_cfg())
    cfg = compose_cfg("init=checkpoints", f"init.detector={weights}")
    parts = stage_parts(cfg, "detector")
    # smoke: 1 epoch from scratch -> 1; lr a third of 2e-3; the EMA of conf/init/_finetune.yaml
    assert parts.config["init"]["train"] == {"epochs": 1, "lr": pytest.approx(2e-3 / 3), "warmup_fraction": 0.05,
                                             "ema_decay": 0.99, "freeze": []}
    assert parts.inputs[INIT_INPUT].startswith("sha256:") and parts.files[INIT_INPUT] == str(weights)
    assert parts.tags["init.source"] == "checkpoints" and parts.tags["init.detector_sha256"] in parts.inputs[INIT_INPUT]
    assert stage_parts(cfg, "relation").key == stage_parts(compose_cfg(), "relation").key  # relation: from scratch

    # the same weights elsewhere: the same key (content, not path); other weights: another key
    copy = tmp_path / "b" / "detector_out"
    copy.mkdir(parents=True)
    shutil.copy(weights, copy / "model.pt")
    assert stage_parts(compose_cfg("init=checkpoints", f"init.detector={copy}"), "detector").key == parts.key
    other = tiny_detector_weights(tmp_path / "c" / "model.pt", compose_cfg(), scale=0.5)
    assert stage_parts(compose_cfg("init=checkpoints", f"init.detector={other}"), "detector").key != parts.key
    budget = compose_cfg("init=checkpoints", f"init.detector={weights}", "init.detector_train.epochs=3")
    assert stage_parts(budget, "detector").key != parts.key


def test_whole_budget_trains_the_from_scratch_epochs(tmp_path):
    """init.budget=whole: a null epochs takes all of the from-scratch epochs (a tenth by default), for both networks;
    a given epochs still wins; an unknown budget is a plan-time error naming the key."""
    weights = tiny_detector_weights(tmp_path / "model.pt", compose_cfg())
    start = ["init=checkpoints", f"init.detector={weights}", "detector.epochs=30", "relation.train.epochs=20"]

    def trained(*overrides):
        return stage_parts(compose_cfg(*start, *overrides), "detector").config["init"]["train"]["epochs"]

    assert trained() == 3 and trained("init.budget=whole") == 30
    assert trained("init.budget=whole", "init.detector_train.epochs=7") == 7
    from stages.relation.warm_start import budget as relation_budget

    for name, epochs in (("tenth", 2), ("whole", 20)):
        cfg = compose_cfg(*start, f"init.budget={name}")
        assert relation_budget(dict(cfg.init.relation_train), cfg)["epochs"] == epochs
    with pytest.raises(PipelineError, match="init.budget=all: expected one of tenth, whole"):
        trained("init.budget=all")


def test_missing_and_incompatible_weights_fail_at_plan_time(tmp_path):
    with pytest.raises(PipelineError, match=r"stage 'detector': init.detector=.*nowhere.pt: no such file"):
        stage_parts(compose_cfg("init=checkpoints", f"init.detector={tmp_path / 'nowhere.pt'}"), "detector")
    weights = tiny_detector_weights(tmp_path / "model.pt", compose_cfg())
    with pytest.raises(PipelineError, match=r"first mismatch at 'backbone\.stem\.0\.weight': checkpoint "
                                            r"\[16, 3, 3, 3\], configured model \[64, 3, 7, 7\]; set detector/backbone"):
        stage_parts(compose_cfg("init=checkpoints", f"init.detector={weights}", "detector/backbone=resnet18"),
                    "detector")
    (tmp_path / "junk.pt").write_text("not weights")
    with pytest.raises(PipelineError, match="cannot read .*junk.pt as detector weights"):
        stage_parts(compose_cfg("init=checkpoints", f"init.detector={tmp_path / 'junk.pt'}"), "detector")


def test_bad_run_ids_fail_at_plan_time(tmp_path, mlflow_template):
    from mlflow.tracking import MlflowClient

    db = tmp_path / "mlflow.db"
    shutil.copyfile(mlflow_template, db)
    uri = f"sqlite:///{db}"
    client = MlflowClient(uri)
    exp = client.create_experiment("deepword", artifact_location=(tmp_path / "artifacts").as_uri())
    context = PlanContext(tmp_path / "cache", uri)

    def plan(run_id: str):
        cfg = compose_cfg("init=run", f"init.run={run_id}", f"tracking.uri={uri}", "init.networks=[detector]")
        return stage_parts(cfg, "detector", context)

    with pytest.raises(PipelineError, match="init.run=0123abcd: no such run in the MLflow store"):
        plan("0123abcd")
    lonely = client.create_run(exp, run_name="data only").info.run_id
    client.set_terminated(lonely)
    with pytest.raises(PipelineError, match=f"pipeline run {lonely} has no 'detector' stage run"):
        plan(lonely)
    parent = client.create_run(exp, run_name="parent").info.run_id
    child = client.create_run(exp, run_name="detector", tags={"mlflow.parentRunId": parent, "stage": "detector",
                                                             "cache_key": "f" * 64}).info.run_id
    client.set_terminated(child)
    with pytest.raises(PipelineError, match=r"cache entry of its 'detector' stage \(detector/ffffffffff...\) is gone"):
        plan(parent)
    with pytest.raises(PipelineError, match="is gone"):
        plan(child)  # a stage run's id stands for its pipeline run


@pytest.fixture(scope="module")
def parent_run(tmp_path_factory):
    """One tiny smoke pipeline (data, priors, relation, detector) from scratch, tracked in its own store."""
    from pipeline.runner import run_pipeline
    from tests.experiments.pipeline_runs import artifacts_beside_store
    from tests.sqlite_store import fresh_store

    tmp = tmp_path_factory.mktemp("init_parent")
    uri = fresh_store(tmp / "mlflow.db")
    artifacts_beside_store(uri, tmp / "artifacts")
    common = [f"tracking.uri={uri}", f"pipeline.cache_dir={tmp / 'cache'}"]
    summary = run_pipeline(compose_cfg(*common), run_dir=tmp / "run0", in_process_tracking=True)
    return {"tmp": tmp, "uri": uri, "common": common, "summary": summary}


def _state(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def _distance(a: dict, b: dict) -> float:
    return sum(float((a[k].float() - b[k].float()).abs().sum()) for k in a if a[k].is_floating_point())


def test_a_run_starts_from_its_parents_weights(parent_run):
    """init=run on another data config and another training seed: both networks end far nearer the parent's
    weights than the same training from scratch does (their random weights are the seed's, not the parent's),
    their first validation differs from scratch's, the tags name the parent, and the same parent hits."""
    from mlflow.tracking import MlflowClient

    from pipeline.runner import run_pipeline
    from stages.training.init_source import file_sha256

    tmp, parent = parent_run["tmp"], parent_run["summary"]
    other = [*parent_run["common"], "data.frames=6", "relation.train.seed=7", "detector.seed=7"]
    overrides = [*other, "init=run", f"init.run={parent['mlflow_run_id']}"]
    summary = run_pipeline(compose_cfg(*overrides), run_dir=tmp / "run1", in_process_tracking=True)
    stages = summary["stages"]
    assert not stages["relation"]["hit"] and not stages["detector"]["hit"]
    scratch = run_pipeline(compose_cfg(*other), run_dir=tmp / "run2", in_process_tracking=True)["stages"]

    for stage, weights in (("detector", "model.pt"), ("relation", "relation.pt")):
        start = _state(Path(parent["stages"][stage]["output_dir"]) / weights)
        tuned = _state(Path(stages[stage]["output_dir"]) / weights)
        from_scratch = _state(Path(scratch[stage]["output_dir"]) / weights)
        assert 0 < _distance(tuned, start) < 0.2 * _distance(from_scratch, start), stage
    # the first (only) validation: not what training from scratch on the same data gives
    first = ("detector.val.ap50.vehicle", "relation.val.wheel_acc")
    assert [stages[k.split(".")[0]]["metrics"][k] for k in first] != [scratch[k.split(".")[0]]["metrics"][k]
                                                                       for k in first]

    client = MlflowClient(parent_run["uri"])
    tags = client.get_run(summary["mlflow_run_id"]).data.tags
    assert tags["init.source"] == "run" and tags["init.source_run"] == parent["mlflow_run_id"]
    assert tags["init.detector_run"] == parent["stages"]["detector"]["mlflow_run_id"]
    assert parent["mlflow_run_id"] in tags["mlflow.note.content"]
    for stage in ("detector", "relation"):
        child = client.get_run(stages[stage]["mlflow_run_id"]).data.tags
        weights = Path(parent["stages"][stage]["output_dir"]) / ("model.pt" if stage == "detector" else "relation.pt")
        assert child[f"init.{stage}_sha256"] == tags[f"init.{stage}_sha256"] == file_sha256(weights)
        assert child["init.source_run"] == parent["mlflow_run_id"]

    again = run_pipeline(compose_cfg(*overrides), run_dir=tmp / "run3", in_process_tracking=True)["stages"]
    assert again["relation"]["hit"] and again["detector"]["hit"]


def test_a_bad_run_id_stops_the_pipeline_before_any_stage(parent_run):
    from pipeline.runner import run_pipeline

    tmp = parent_run["tmp"]
    cache = tmp / "cache_bad"
    cfg = compose_cfg(f"tracking.uri={parent_run['uri']}", f"pipeline.cache_dir={cache}", "init=run",
                      "init.run=feedface")
    with pytest.raises(PipelineError, match="stage 'relation': init.run=feedface: no such run"):
        run_pipeline(cfg, run_dir=tmp / "run_bad", in_process_tracking=True)
    assert not any((cache / s).is_dir() and any(p for p in (cache / s).iterdir() if not p.name.startswith("."))
                   for s in ("data", "priors"))


def test_relation_members_start_from_as_many_members_or_one_network(tmp_path):
    from stages.relation.warm_start import member_states
    from stages.training.init_source import InitError

    one = {"backbone.w": torch.zeros(2), "gcn.0.weight": torch.ones(2, 2)}
    two = {f"members.{i}.{k}": v + i for i in range(2) for k, v in one.items()}
    assert [torch.equal(m["backbone.w"], torch.full((2,), float(i))) for i, m in
            enumerate(member_states(two, 2, tmp_path))] == [True, True]
    assert len(member_states(one, 3, tmp_path)) == 3
    with pytest.raises(InitError, match="holds an ensemble of 2 networks, the config asks for 3: set relation.ensemble=2"):
        member_states(two, 3, tmp_path)


def test_relation_fine_tuning_selects_its_checkpoint_by_the_val_loss():
    """A fine-tuning starts at the plateau of val wheel_acc, where the first epoch would win every tie: its
    budget selects on the val loss unless told otherwise, and the stage trains with what the budget says."""
    from stages.relation.warm_start import budget, fine_tuning

    cfg = compose_cfg("init=run", "init.run=abc")
    assert cfg.relation.train.select == "wheel_acc"                       # from scratch: unchanged
    filled = budget(dict(OmegaConf.to_container(cfg.init.relation_train)), cfg)
    assert filled["select"] == "loss"
    assert fine_tuning(cfg, filled).relation.train.select == "loss"
    assert budget({"select": None}, cfg)["select"] == "wheel_acc"         # null: as relation.train.select
    assert fine_tuning(cfg, budget({"select": "wheel_acc"}, cfg)).relation.train.select == "wheel_acc"


def test_a_frozen_backbone_keeps_the_parents_weights_and_statistics(parent_run):
    """init.detector_train.freeze=[backbone]: the backbone's weights and batch-norm statistics come out as the parent
    left them, the heads learn; an unknown part is a plan-time error."""
    from pipeline.runner import run_pipeline
    from stages.detector.warm_start import budget
    from stages.training.init_source import InitError

    tmp, parent = parent_run["tmp"], parent_run["summary"]
    overrides = [*parent_run["common"], "data.frames=6", "detector.seed=7", "init=run",
                 f"init.run={parent['mlflow_run_id']}", "init.networks=[detector]",
                 "init.detector_train.freeze=[backbone]", "pipeline.until=detector"]
    stages = run_pipeline(compose_cfg(*overrides), run_dir=tmp / "run_frozen", in_process_tracking=True)["stages"]
    start = _state(Path(parent["stages"]["detector"]["output_dir"]) / "model.pt")
    tuned = _state(Path(stages["detector"]["output_dir"]) / "model.pt")
    backbone = [k for k in start if k.startswith("backbone.")]
    assert any(k.endswith("running_mean") for k in backbone)
    assert all(torch.equal(start[k], tuned[k]) for k in backbone)
    assert _distance({k: v for k, v in tuned.items() if k.startswith("heads.")}, start) > 0

    with pytest.raises(InitError, match=r"unknown part\(s\) \['neck'\]"):
        budget({"freeze": ["neck"]}, compose_cfg("init=run", "init.run=abc"))
