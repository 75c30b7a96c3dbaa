"""relation.distill: the student's loss against its teachers, its module, and the stage shipping it."""

import json

import pytest
import torch
from omegaconf import OmegaConf

from stages.relation.distill import DistillConfig
from stages.relation.lightning import GraphDataset, collate_graphs
from stages.relation.student import DistilledRelationModule, distillation_loss
from tests.stages.relation.test_relation_training import (
    DECODE,
    LOSS,
    TINY,
    _module,
    _run_stage,
    _split,
    _write_dataset,
)

torch.set_num_threads(1)


def _batch(n: int = 4, seed: int = 0):
    split = _split(n, seed)
    return collate_graphs([GraphDataset(split)[i] for i in range(len(split))])


def _student(distill: dict | None = None) -> DistilledRelationModule:
    from dataclasses import asdict

    torch.manual_seed(1)
    return DistilledRelationModule(model=asdict(TINY), loss={**LOSS, "rank_weight": 0.5}, decode=dict(DECODE),
                                   optim={"lr": 1e-3, "weight_decay": 0.0}, distill=distill)


def test_the_teachers_term_is_zero_where_the_student_answers_as_they_do_and_grows_with_the_difference():
    batch = _batch()
    teacher = tuple(t.detach() for t in _module()(batch))
    assert float(distillation_loss(teacher, teacher, batch, 0.1, 0.5, 0.8)) == pytest.approx(0.0, abs=1e-6)
    owner, couple, front = teacher
    nudged = (owner + 0.1 * torch.randn_like(owner), couple, front.clamp(0.2, 0.8))
    far = (owner + 0.5 * torch.randn_like(owner), couple, front)
    small = float(distillation_loss(nudged, teacher, batch, 0.1, 0.5, 0.8))
    assert 0 < small < float(distillation_loss(far, teacher, batch, 0.1, 0.5, 0.8))


def test_the_student_trains_alone_and_its_teachers_stay_frozen_and_out_of_its_weights():
    teachers = [_module(), _module(lr=1e-3)]
    before = [{k: v.clone() for k, v in t.state_dict().items()} for t in teachers]
    student = _student()
    with pytest.raises(RuntimeError, match="no teachers"):
        student.training_step(_batch(), 0)
    student.teach(teachers)
    assert set(student.state_dict()) == set(teachers[0].state_dict())  # no teacher weights in its checkpoint
    assert sum(p.numel() for p in student.parameters()) == sum(p.numel() for p in teachers[0].parameters())
    student.train()
    student.log = lambda *args, **kwargs: None  # outside a Trainer
    loss = student.training_step(_batch(), 0)
    loss.backward()
    assert all(not t.training for t in teachers)
    assert all(p.grad is None for t in teachers for p in t.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in student.parameters())
    assert all(torch.equal(before[i][k], v) for i, t in enumerate(teachers) for k, v in t.state_dict().items())


@pytest.mark.parametrize("node, message", [
    ({"enabled": True, "weight": -1.0}, "must be >= 0"),
    ({"enabled": True, "weight": 0.0, "label_weight": 0.0}, "not both 0"),
    ({"enabled": True, "start": "teacher"}, "relation.distill.start must be one of"),
])
def test_a_bad_distill_config_names_its_field(node, message):
    with pytest.raises(ValueError, match=message):
        DistillConfig.from_cfg(OmegaConf.create(node))


@pytest.mark.slow
def test_the_stage_ships_one_student_taught_by_the_members(tmp_path):
    """relation.ensemble=2 with relation.distill.enabled: the two members train, then a student from the next seed;
    relation.pt holds that one network (load_network: a RelationNet), relation.json says what it was distilled
    from, and the metrics hold the teachers' val scores beside the shipped network's."""
    from stages.relation import stage
    from stages.relation.model import RelationNet

    _write_dataset(tmp_path)
    metrics, out = _run_stage(tmp_path, "distilled", epochs=1, ensemble=2, distill={"enabled": True})
    meta = json.loads((out / "relation.json").read_text())
    assert meta["ensemble"] == 1 and meta["distilled_from"] == 2 and meta["seeds"] == [0, 1]
    assert len(meta["student_curves"]) == 1
    assert {"relation.teachers.val.wheel_acc", "relation.member1.val.wheel_acc", "relation.val.wheel_acc",
            "relation.student.epochs"} <= set(metrics)
    assert sorted(p.name for p in out.iterdir()) == ["artifacts", "relation.json", "relation.pt"]
    assert (out / "artifacts" / "relation_student_curves.png").stat().st_size > 1000
    net, _ = stage.load_network(out)
    assert isinstance(net, RelationNet)
    _, lone = _run_stage(tmp_path, "lone_seed_2", epochs=1, seed=2)  # the student's seed, without teachers
    alone = torch.load(lone / "relation.pt", weights_only=True)
    assert any(not torch.equal(alone[k], v) for k, v in net.state_dict().items())  # the teachers moved it
