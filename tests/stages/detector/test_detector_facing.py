"""The detector's facing head end to end: the image direction of a vehicle's front (deepword/facing.py) as a training
target that follows the flip, its loss and val agreement, its decoding into (B, K, 8) detections and into detection
records (ids renumbered with their facings), a start without the head, and the footprints' vote that turns a heading
the wheels left backwards."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from deepword.detection.letterbox import letterbox_for
from deepword.detection.records import detections_to_record, renumbered
from deepword.facing import FACING_KEY, box_facings, image_facing, record_facing
from deepword.footprint import FACING_LOGIT, Estimate, facing_vote, fuse_frame
from deepword.format_3d import Box3D
from deepword.word_format import Record
from stages.detector.dataset import box_labels
from stages.detector.decode import decode_outputs
from stages.detector.losses import detector_loss, facing_agreement
from stages.detector.model import build_centernet
from stages.detector.targets import centernet_targets, facing_targets
from tests.stages.bev.test_bev import _camera


def _calibrated_record(cam, vehicle: Box3D) -> Record:
    boxes = np.array([[100.0, 100.0, 300.0, 220.0, 1.0, 0, 0], [120.0, 190.0, 150.0, 220.0, 1.0, 1, 1]])
    objects = {"0": {"center": [vehicle.x, vehicle.y, vehicle.height / 2],
                     "size": [vehicle.length, vehicle.width, vehicle.height], "yaw": vehicle.yaw},
               "1": {"contact": [vehicle.x, vehicle.y]}}
    return Record(image="images/left/000000.png", frame_id=0, camera="left", width=cam.width, height=cam.height,
                  boxes=boxes, relations=[(0, 1, None)], wheel_pairs=[],
                  extra={"calibration": cam.calibration(), "objects_3d": objects})


def test_image_facing_points_from_rear_to_front_and_turns_with_the_vehicle():
    cam = _camera()                       # the left camera, looking along +y
    v = Box3D(0.5, 5.0, 4.5, 1.8, 0.0, 1.5)  # beside the car, facing +x (the way the ego drives)
    ahead = image_facing(cam, v.x, v.y, v.yaw, v.length)
    back = image_facing(cam, v.x, v.y, math.pi, v.length)
    assert ahead is not None and np.hypot(*ahead) == pytest.approx(1.0)
    assert back == pytest.approx(-ahead, abs=1e-9)
    # the left camera looks out to the car's left: the car's front (+x) lies to the image's right
    assert ahead[0] > 0.5
    assert image_facing(cam, -0.2, -30.0, 0.0, 4.5) is None  # behind the camera: outside its field of view


def test_image_facing_of_a_vehicle_seen_end_on_points_down_to_the_nearer_end_whatever_its_height():
    # on the ground the nearer of two points projects lower in the image; the vehicle's height plays no part (the
    # faces' centres at half height lie near a camera's height, where which projects lower turned on that height)
    cam = _camera()                       # the left camera at (0.85, 1.05, 1.0 m), looking along +y
    away = image_facing(cam, 0.85, 6.0, math.pi / 2, 4.5)     # front to the far end: up the image
    towards = image_facing(cam, 0.85, 3.5, -math.pi / 2, 4.5)  # front to the near end, close by: down the image
    assert away is not None and towards is not None
    assert away[1] < -0.99 and towards[1] > 0.99


def test_targets_come_from_the_3d_truth_and_a_flip_mirrors_them():
    cam = _camera()
    v = Box3D(0.5, 5.0, 4.5, 1.8, 0.0, 1.5)
    rec = _calibrated_record(cam, v)
    facings = box_facings(rec)
    assert facings[0] == pytest.approx(image_facing(cam, v.x, v.y, v.yaw, v.length))
    assert np.isnan(facings[1]).all()                                   # a wheel has none
    plain = replace(rec, extra={})
    assert np.isnan(box_facings(plain)).all()                           # 2D labels: none, and no error
    labels = box_labels(rec, facings, flipped=True)
    assert labels[0, 1] == pytest.approx(-facings[0, 0]) and labels[0, 2] == pytest.approx(facings[0, 1])
    assert labels[:, 0].tolist() == [0, 1]
    t = centernet_targets(rec.xyxy / 4, rec.class_ids, 2, 160, 120, 4)
    f = facing_targets(facings, t["mask"])
    assert f["facing_mask"].tolist() == [1, 0, 0, 0] and f["facing"][0] == pytest.approx(facings[0])


def test_a_start_without_the_facing_head_loads_and_the_head_starts_fresh(tmp_path):
    from stages.detector.warm_start import load_start, without_new_facing
    from tests.stages.detector.test_detector_model import TINY, config

    old = build_centernet({**config(TINY, regression="ttfnet"), "facing": False})
    new = build_centernet({**config(TINY, regression="ttfnet"), "facing": True})
    path = tmp_path / "model.pt"
    torch.save(old.state_dict(), path)
    expected = new.state_dict()
    assert set(without_new_facing(expected, old.state_dict())) == set(old.state_dict())
    assert without_new_facing(expected, expected) is expected
    before = new.heads.facing[-1].weight.clone()
    load_start(new, path)
    assert torch.equal(new.heads.hm[-1].weight, old.heads.hm[-1].weight)
    assert torch.equal(new.heads.facing[-1].weight, before)
    out = new.eval()(torch.zeros(1, 3, 32, 64))
    assert len(out) == 3 and out[-1].shape == (1, 2, 8, 16) and new.decode(out, 5).shape == (1, 5, 8)


def test_loss_decoding_and_agreement_read_the_facing_map_at_the_centre_cells():
    heat = torch.full((1, 2, 8, 8), 0.01)
    heat[0, 0, 3, 5] = 0.9
    ltrb = torch.ones((1, 4, 8, 8))
    facing = torch.zeros((1, 2, 8, 8))
    facing[0, :, 3, 5] = torch.tensor([0.6, -0.8])
    dets = decode_outputs((heat, ltrb, facing), k=3, down_ratio=4, regression="ttfnet", facing=True)
    assert dets.shape == (1, 3, 8) and dets[0, 0, 6:].tolist() == pytest.approx([0.6, -0.8])
    assert torch.equal(dets[..., :6], decode_outputs((heat, ltrb), k=3, down_ratio=4))
    batch = {"hm": torch.zeros((1, 2, 8, 8)), "box": torch.zeros((1, 4, 8, 8)), "box_weight": torch.zeros((1, 8, 8)),
             "ind": torch.tensor([[3 * 8 + 5, 0]]), "mask": torch.tensor([[1.0, 0.0]]),
             "facing": torch.tensor([[[0.6, -0.8], [0.0, 0.0]]]), "facing_mask": torch.tensor([[1.0, 0.0]])}
    weights = {"facing_weight": 0.5}
    _, parts = detector_loss((heat, ltrb, facing), batch, "ttfnet", 4, weights)
    assert float(parts["facing"]) == pytest.approx(0.0, abs=1e-6)
    batch["facing"] = -batch["facing"]
    total, parts = detector_loss((heat, ltrb, facing), batch, "ttfnet", 4, weights)
    plain, _ = detector_loss((heat, ltrb), batch, "ttfnet", 4, weights)
    assert float(parts["facing"]) == pytest.approx(1.4, rel=1e-3) and float(total - plain) == pytest.approx(0.7, rel=1e-3)
    assert facing_agreement(facing, batch).tolist() == [[0.0, 1.0]]
    batch["facing_mask"] = torch.zeros((1, 2))
    _, parts = detector_loss((heat, ltrb, facing), batch, "ttfnet", 4, weights)
    assert float(parts["facing"]) == 0.0                                # no target in the batch: no loss


def test_detection_records_carry_the_vehicles_facings_through_the_operating_point():
    source = Record(image="a.png", frame_id=0, camera="left", width=128, height=128, boxes=np.zeros((0, 7)),
                    relations=[], wheel_pairs=[])
    dets = np.array([[10, 10, 50, 50, 0.9, 0, 0.6, -0.8], [60, 60, 70, 70, 0.8, 1, 0.3, 0.1],
                     [20, 70, 60, 110, 0.5, 0, -1.0, 0.0], [0, 0, 5, 5, 0.05, 0, 1.0, 0.0]], dtype=np.float32)
    rec = detections_to_record(dets, source, letterbox_for(128, 128, 128, 128), 0.1)
    assert record_facing(rec) == {0: pytest.approx([0.6, -0.8]), 2: pytest.approx([-1.0, 0.0])}  # vehicles only
    again = Record(**{**rec.__dict__, "boxes": rec.boxes[[0, 2]].copy()})
    assert record_facing(renumbered(again)) == {0: pytest.approx([0.6, -0.8]), 1: pytest.approx([-1.0, 0.0])}
    assert FACING_KEY not in detections_to_record(dets[:, :6], source, letterbox_for(128, 128, 128, 128), 0.1).extra


def test_the_facing_vote_turns_a_backwards_heading():
    cam = _camera()
    truth = Box3D(0.5, 5.0, 4.5, 1.8, 0.0, 1.5)
    seen = image_facing(cam, truth.x, truth.y, truth.yaw, truth.length)
    assert facing_vote(cam, truth, list(seen)) == pytest.approx(FACING_LOGIT)
    backwards = replace(truth, yaw=math.pi)
    assert facing_vote(cam, backwards, list(seen * 0.5)) == pytest.approx(-0.5 * FACING_LOGIT)
    assert facing_vote(cam, truth, None) == 0.0 and facing_vote(cam, truth, [0.0, 0.0]) == 0.0
    estimate = Estimate(backwards, "side", "left", 0, "l.png", 0.9, facing_vote=facing_vote(cam, backwards, list(seen)))
    assert estimate.directed
    (box, _), = fuse_frame([estimate], 1.5)
    assert abs(math.remainder(box.yaw - truth.yaw, 2 * math.pi)) < 1e-9


def test_the_bev_stage_scores_how_often_the_facing_points_the_right_way():
    from stages.bev.metrics import facing_agreement

    cam = _camera()
    rec = _calibrated_record(cam, Box3D(0.5, 5.0, 4.5, 1.8, 0.0, 1.5))
    seen = box_facings(rec)[0]
    pred = replace(rec, boxes=rec.boxes.copy(), relations=[], extra={FACING_KEY: {"0": list(seen * 0.7)}})
    assert facing_agreement([rec], {rec.image: pred}) == {"acc": 100.0, "vehicles": 1.0}
    wrong = replace(pred, extra={FACING_KEY: {"0": list(-seen)}})
    assert facing_agreement([rec], {rec.image: wrong}) == {"acc": 0.0, "vehicles": 1.0}
    assert facing_agreement([rec], {rec.image: replace(pred, extra={})}) is None     # no facing head: no score
    moved = replace(pred, boxes=pred.boxes + [200, 0, 200, 0, 0, 0, 0])              # matches nothing
    assert facing_agreement([rec], {rec.image: moved}) is None
