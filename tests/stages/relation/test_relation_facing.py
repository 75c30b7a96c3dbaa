"""The relation network's facing head: targets from the 3D truth in the cached split inputs (turned by the training
flip), its loss and val count, a start from a network without it, the predictions that carry its vectors with the
accuracy measured on val, and the footprints' vote that trusts them by that accuracy."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from deepword.facing import FACING_ACC_KEY, FACING_KEY, box_facings, record_facing, record_facing_accuracy
from deepword.footprint import FACING_LOGIT, facing_logit, facing_vote
from deepword.format_3d import Box3D
from deepword.inference.decode import prediction_record
from deepword.relation_graph import InputConfig, build_split
from stages.relation.decode import facing_counts
from stages.relation.lightning import GraphDataset
from stages.relation.losses import facing_loss
from stages.relation.model import ModelConfig, RelationNet
from stages.relation.stage import facing_val_acc
from tests.stages.bev.test_bev import _camera
from tests.stages.detector.test_detector_facing import _calibrated_record
from tests.stages.relation import relation_data as rd
from tests.stages.relation.test_relation_model import conv_fc

VEHICLE_AHEAD = Box3D(0.5, 5.0, 4.5, 1.8, 0.0, 1.5)   # beside the car on its left, facing the way it drives


def _split(records):
    def black(rec):
        return np.zeros((rec.height, rec.width, 3), np.uint8)

    return build_split(records, black, InputConfig(input_size=16, max_objects=4), rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL)


def test_split_inputs_carry_each_vehicles_facing_and_the_training_flip_turns_it():
    rec = _calibrated_record(_camera(), VEHICLE_AHEAD)
    split = _split([rec, replace(rec, image="images/left/000001.png", extra={})])
    truth = box_facings(rec)[0]
    assert split.facing[0, 0] == pytest.approx(truth) and np.abs(truth).sum() > 0
    assert split.facing[0, 1:].tolist() == [[0.0, 0.0]] * 3          # the wheel, padding: none
    assert not split.facing[1].any()                                  # 2D labels only: nothing to learn from
    flipped = GraphDataset(split, hflip=1.0)[0]["facing"]
    assert flipped[0].tolist() == pytest.approx([-truth[0], truth[1]])
    alone = replace(rec, image="images/left/000002.png", boxes=rec.boxes[:1], relations=[])  # one node: (1, 2)
    assert GraphDataset(_split([alone]))[0]["facing"].numpy() == pytest.approx(truth[None])


def test_the_facing_loss_and_count_reward_the_right_direction_only_where_there_is_a_target():
    target = torch.tensor([[[0.6, 0.8], [0.0, 0.0]]])                 # a vehicle with 3D truth; a node without
    batch = {"facing": target, "valid": torch.tensor([[True, True]])}
    right = torch.tensor([[[1.2, 1.6], [5.0, 5.0]]])
    wrong = torch.tensor([[[-1.2, -1.6], [5.0, 5.0]]])
    assert facing_loss(right, batch) < 0.01 < 3.0 < facing_loss(wrong, batch)
    assert facing_loss(right, {**batch, "facing": torch.zeros_like(target)}) == 0.0
    assert {k: int(v) for k, v in facing_counts(right, target, batch["valid"]).items()} == \
        {"facing_right": 1, "facing_known": 1}
    assert int(facing_counts(wrong, target, batch["valid"])["facing_right"]) == 0


def test_a_start_without_the_facing_head_loads_and_the_head_starts_fresh():
    from stages.relation.warm_start import load_start, without_new_facing

    cfg = ModelConfig(backbone=conv_fc(16), hidden=32, embed_dim=16, gat_hidden=16)
    new = RelationNet(cfg)
    old = {k: v for k, v in RelationNet(cfg).state_dict().items() if not k.startswith("facing_head.")}
    assert set(without_new_facing(new.state_dict(), old)) == set(old)
    before = new.facing_head.weight.clone()
    load_start(new, old)
    assert torch.equal(new.owner_head.weight, old["owner_head.weight"])
    assert torch.equal(new.facing_head.weight, before)
    with pytest.raises(RuntimeError, match="owner_head"):
        load_start(new, {k: v for k, v in old.items() if not k.startswith("owner_head.")})


def test_predictions_carry_the_vectors_with_their_measured_accuracy_and_the_vote_trusts_it():
    cam = _camera()
    rec = _calibrated_record(cam, VEHICLE_AHEAD)
    truth = box_facings(rec)[0]
    owner = np.zeros((2, 2), bool)
    facing = np.array([truth * 2.0, [9.0, 9.0]], np.float32)          # the wheel's vector is not written
    pred = prediction_record(rec, owner, owner, np.full(2, 0.5), True, facing, 0.9)
    assert record_facing(pred) == {0: pytest.approx(list(truth * 2.0), abs=1e-4)}
    assert record_facing_accuracy(pred, 0.57) == pytest.approx(0.9)
    unmeasured = prediction_record(rec, owner, owner, np.full(2, 0.5), True, facing, None)
    assert FACING_KEY not in unmeasured.extra and FACING_ACC_KEY not in unmeasured.extra
    assert record_facing_accuracy(unmeasured, 0.57) == 0.57           # a detector's vectors: its own constant
    assert facing_vote(cam, VEHICLE_AHEAD, list(truth), 0.9) == pytest.approx(math.log(9.0))
    backwards = replace(VEHICLE_AHEAD, yaw=math.pi)
    assert facing_vote(cam, backwards, list(truth), 0.9) == pytest.approx(-math.log(9.0))
    assert facing_vote(cam, VEHICLE_AHEAD, list(truth), 0.4) == 0.0    # at or below chance: no vote
    assert facing_vote(cam, VEHICLE_AHEAD, list(truth)) == pytest.approx(FACING_LOGIT)
    assert facing_logit(1.0) == pytest.approx(math.log(99.0))           # a perfect val score is still a sample


def test_only_a_trained_head_has_a_val_accuracy_to_ship():
    rel = OmegaConf.create({"loss": {"facing_weight": 0.2}})
    assert facing_val_acc(rel, {"facing_acc": 87.5}) == 87.5
    assert facing_val_acc(rel, {}) is None                             # val without 3D truth
    assert facing_val_acc(OmegaConf.create({"loss": {"facing_weight": 0.0}}), {"facing_acc": 50.0}) is None
