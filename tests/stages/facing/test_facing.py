"""The facing network: its crops and targets from the 3D truth, the crop <-> image vectors, the stage on renders of
the project's own generator (a few frames, two epochs), its export checked against PyTorch, the runtime that writes
each vehicle's vector and val accuracy into records (the bev stage: each image decoded once for all its box
sources), a dataset without 3D truth that learns from its couples' labelled roles, and one without either (no
network, no vectors)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from deepword.facing import box_facings, record_facing, record_facing_accuracy
from deepword.facing_crop import to_crop, to_image
from deepword.inference.facing_net import OnnxFacing, vehicle_crops
from deepword.relation_graph import crop_objects
from deepword.word_format import difficulty_subsets, write_dataset_index, write_records
from stages.facing.model import FacingNet, facing_loss
from stages.facing.stage import CONFIG_FILE, WEIGHTS_FILE, augment, split_crops
from stages.facing.stage import run as run_facing

FACING_CFG = {"input_size": 24, "margin": 0.1, "widths": [4, 8], "hidden": 8,
              "train": {"epochs": 2, "batch_size": 16, "lr": 0.003, "weight_decay": 0.0001, "box_jitter": 0.08,
                        "threads": 1, "channels_last": True, "seed": 0, "limit_train_images": None}}
TRAINER = {"accelerator": "cpu", "precision": "32-true"}


def _stage_cfg(**facing) -> OmegaConf:
    return OmegaConf.create({"facing": {**FACING_CFG, **facing}, "trainer": TRAINER, "seed": 0})


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    """A data-stage-like directory of four frames of the generator (16 images at 320x240 with 3D truth)."""
    from stages.data.synword import FrameGenerator

    cfg = OmegaConf.to_container(OmegaConf.load(Path(__file__).parents[3] / "conf/data/synword.yaml"), resolve=True)
    cfg["image_size"] = [320, 240]
    cfg["lens"]["randomise"] = False
    root = tmp_path_factory.mktemp("rendered")
    records = []
    for frame in range(4):
        for camera, rgb, rec in FrameGenerator(cfg, seed=3).render_frame(frame):
            rec = replace(rec, image=f"images/{camera}/{frame:06d}.png")
            (root / rec.image).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / rec.image), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            records.append(rec)
    write_records(root / "labels.jsonl", records)
    images = [r.image for r in records]
    splits = {"train": images[:8], "val": images[8:12], "test": images[12:]}
    splits.update(difficulty_subsets(records[12:], 0))
    write_dataset_index(root, root, splits)
    return root


def test_vectors_go_into_the_squeezed_crop_and_back_with_their_length():
    boxes = np.array([[0.0, 0.0, 200.0, 50.0], [10.0, 10.0, 30.0, 30.0]])
    image = np.array([[1.0, 1.0], [0.0, -1.0]]) / np.sqrt([[2.0], [1.0]])   # unit directions
    crop = to_crop(image, boxes, 0.1)
    assert crop[0] == pytest.approx(np.array([0.25, 1.0]) / np.hypot(0.25, 1.0))   # a wide box: x squeezed 4:1
    assert np.linalg.norm(crop, axis=1) == pytest.approx([1.0, 1.0])
    back = to_image(crop * np.array([[2.0], [0.5]]), boxes, 0.1)                   # lengths: the certainty, kept
    assert back == pytest.approx(image * np.array([[2.0], [0.5]]), abs=1e-6)


def test_train_crops_come_from_the_3d_truth_once_as_labelled_and_once_jittered(rendered):
    from deepword.word_format import open_dataset

    ds = open_dataset(rendered)
    records = ds.subset("train")
    known = sum(int(np.isfinite(box_facings(r)).all(axis=1).sum()) for r in records)
    assert known > 0
    crops, targets = split_crops(records, ds.root, 24, 0.1, 0.08, np.random.default_rng(0))
    assert crops.shape == (2 * known, 3, 24, 24) and crops.dtype == np.uint8
    assert np.linalg.norm(targets, axis=1) == pytest.approx(np.ones(2 * known), abs=1e-5)
    plain, plain_targets = split_crops(records, ds.root, 24, 0.1, 0.08, None)
    assert len(plain) == known and len(plain_targets) == known
    flat = [replace(r, extra={}) for r in records]                                   # 2D labels only
    assert len(split_crops(flat, ds.root, 24, 0.1, 0.08, None)[0]) == 0


def test_a_padded_crops_centre_is_the_crop_inference_cuts_and_its_target_the_same(rendered, monkeypatch):
    from deepword.word_format import open_dataset

    ds = open_dataset(rendered)
    records = ds.subset("train")
    import stages.facing.stage as facing_stage

    asked = []
    monkeypatch.setattr(facing_stage, "crop_objects", lambda rgb, boxes, size, margin: asked.append((size, margin))
                        or crop_objects(rgb, boxes, size, margin))
    plain, plain_targets = split_crops(records, ds.root, 24, 0.1, 0.0, None)
    assert set(asked) == {(24, 0.1)}                                         # the margin inference cuts with, exactly
    asked.clear()
    padded, padded_targets = split_crops(records, ds.root, 24, 0.1, 0.0, None, pad=3)
    assert {size for size, _ in asked} == {30}
    assert [margin for _, margin in asked] == pytest.approx([0.25] * len(asked))   # 1.2 x 30 / 24 = 1.5 boxes wide
    assert padded.shape == (len(plain), 3, 30, 30)
    assert padded_targets == pytest.approx(plain_targets, abs=1e-6)          # a direction does not see the margin
    centre = padded[:, :, 3:27, 3:27].astype(float)
    # the same scale, resampled on a grid a fraction of a pixel apart: close, and far closer than a window moved
    moved = padded[:, :, 0:24, 0:24].astype(float)
    assert np.abs(centre - plain).mean() < 0.25 * np.abs(moved - plain).mean()


def test_the_shifted_window_is_a_random_translation_of_the_padded_crop():
    b, size, pad = 64, 6, 2
    # distinct values under 100, so that no brightness gain clips them
    crops = (torch.arange(b * 3 * 10 * 10).reshape(b, 3, 10, 10) * 7919).remainder(97).add(1).to(torch.uint8)
    targets = torch.tensor([[0.6, 0.8]]).repeat(b, 1)
    x, y = augment(crops, targets, torch.Generator().manual_seed(0), size)
    assert x.shape == (b, 3, size, size)
    places = []
    for i in range(b):
        window = x[i].flip(-1) if y[i, 0] < 0 else x[i]                  # mirrored: the target's x negated
        assert y[i].abs().tolist() == pytest.approx([0.6, 0.8])
        for oy, ox in np.ndindex(2 * pad + 1, 2 * pad + 1):
            src = crops[i, :, oy:oy + size, ox:ox + size].float()
            gain = window[:, 0, 0] / src[:, 0, 0]                         # brightness x white balance, per channel
            if torch.allclose(window, src * gain[:, None, None], rtol=1e-4):
                places.append((oy, ox))
                break
        else:
            pytest.fail(f"crop {i}: its window is no translation of the padded crop")
    assert len(set(places)) > 10                                             # drawn all over the pad
    plain, _ = augment(crops[:, :, :size, :size], targets, torch.Generator().manual_seed(0), size)
    assert plain.shape == (b, 3, size, size)                                 # no pad: the crop as it is


def test_a_negative_shift_is_refused_before_any_crop_is_cut(rendered, tmp_path):
    cfg = _stage_cfg(train={**FACING_CFG["train"], "shift": -0.1})
    with pytest.raises(ValueError, match=r"facing.train.shift: .* got -0.1"):
        run_facing(cfg, {"data": rendered}, tmp_path)


def test_the_loss_rewards_the_right_direction_and_grows_the_vector_with_certainty():
    target = torch.tensor([[0.6, 0.8]])
    assert facing_loss(torch.tensor([[1.2, 1.6]]), target) < facing_loss(torch.tensor([[0.3, 0.4]]), target) \
        < facing_loss(torch.tensor([[-0.3, -0.4]]), target)
    assert FacingNet((4, 8), 8)(torch.zeros((3, 3, 24, 24), dtype=torch.uint8)).shape == (3, 2)


def test_convs_sets_each_blocks_layers_and_two_keeps_the_weight_names_of_older_networks():
    two = FacingNet((4, 8), 8)
    assert two.state_dict().keys() == FacingNet((4, 8), 8, (2, 2)).state_dict().keys()   # facing.pt of older runs
    one = FacingNet((4, 8), 8, (1, 2))
    convs = [sum(isinstance(m, torch.nn.Conv2d) for m in block) for block in one.features]
    assert convs == [1, 2]
    assert one(torch.zeros((2, 3, 24, 24), dtype=torch.uint8)).shape == (2, 2)
    for bad in ((2,), (0, 2)):
        with pytest.raises(ValueError, match="facing.convs"):
            FacingNet((4, 8), 8, bad)


@pytest.fixture(scope="module")
def trained(rendered, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("facing")
    torch.set_num_threads(1)
    return out, run_facing(_stage_cfg(), {"data": rendered}, out)


def test_the_stage_trains_chooses_on_val_and_is_reproducible(rendered, trained, tmp_path):
    out, metrics = trained
    meta = json.loads((out / CONFIG_FILE).read_text())
    assert meta["trained"] and (out / WEIGHTS_FILE).is_file() and (out / "artifacts/facing_curves.png").is_file()
    assert metrics["facing.val.acc"] == max(r["val/facing_acc"] for r in meta["curves"]) == meta["val_acc"]
    assert metrics["facing.val.vehicles"] > 0 and len(meta["curves"]) == 2
    again = run_facing(_stage_cfg(), {"data": rendered}, tmp_path)
    assert again["facing.val.acc"] == metrics["facing.val.acc"]
    assert torch.load(tmp_path / WEIGHTS_FILE)["head.2.weight"].equal(torch.load(out / WEIGHTS_FILE)["head.2.weight"])


def test_a_tie_on_val_keeps_the_later_epoch(rendered, tmp_path, monkeypatch):
    import stages.facing.stage as facing_stage

    accuracies = iter([[1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [1.0, 1.0]])   # 50 %, 100 %, 50 %, 100 %
    monkeypatch.setattr(facing_stage, "agreement", lambda net, x, y, device: np.array(next(accuracies, [1.0, 1.0])))
    run_facing(_stage_cfg(train={**FACING_CFG["train"], "epochs": 4}), {"data": rendered}, tmp_path)
    assert json.loads((tmp_path / CONFIG_FILE).read_text())["best_epoch"] == 3


def test_exported_it_writes_each_vehicles_vector_and_accuracy_into_records(rendered, trained, tmp_path, monkeypatch):
    from deepword.inference.runtime import BUNDLE_FILE
    from deepword.word_format import load_image, open_dataset
    from stages.export.stage import export_facing_checked
    from stages.facing.stage import load_network

    ds = open_dataset(rendered)
    test = ds.subset("test")
    ex = OmegaConf.create({"latency": {"threads": 1}, "parity": {"max_abs_diff": 1e-4, "min_agreement": 99.0}})
    net, meta = load_network(trained[0])
    crops = np.concatenate([vehicle_crops(load_image(ds.root, r), r, meta["input_size"], meta["margin"])[1] for r in test])
    entry, metrics = export_facing_checked(net, meta, crops, tmp_path, ex)
    assert entry["val_acc"] == trained[1]["facing.val.acc"] and metrics["export.facing.parity_max_abs_diff"] < 1e-4
    (tmp_path / BUNDLE_FILE).write_text(json.dumps({"facing": entry}))
    runtime = OnnxFacing.from_bundle(tmp_path)
    rec = next(r for r in test if (r.class_ids == 0).any())
    rgb = load_image(ds.root, rec)
    annotated = runtime.annotate(rec, rgb)
    vehicles = {int(b) for b, c in zip(rec.box_ids, rec.class_ids, strict=True) if c == 0}
    assert set(record_facing(annotated)) == vehicles
    assert record_facing_accuracy(annotated, 0.5) == pytest.approx(entry["val_acc"] / 100, abs=1e-4)
    rows, crops = vehicle_crops(rgb, rec, entry["input_size"], entry["margin"])
    with torch.no_grad():
        x = torch.from_numpy(crops)
        mean = ((net(x) + net(x.flip(-1)) * torch.tensor([-1.0, 1.0])) / 2).numpy()
    want = to_image(mean, rec.xyxy[rows], entry["margin"])
    got = np.array([record_facing(annotated)[int(rec.box_ids[r])] for r in rows])
    assert got == pytest.approx(want, abs=1e-3)                       # flip-averaged as the stage validated it

    # the bev stage: both box sources' records of an image get their vectors from one decode of it
    import stages.bev.stage as bev

    moved = {r.image: replace(r, boxes=r.boxes + np.array([2.0, 1.0, 2.0, 1.0, 0, 0, 0])) for r in test}
    reads = {"gt": {"logic": {r.image: r for r in test}, "deepword": {r.image: r for r in test}},
             "detected": {"deepword": moved}}
    decoded = []
    monkeypatch.setattr(bev, "load_image", lambda root, r: decoded.append(r.image) or load_image(root, r))
    out = bev.with_facing_vectors(reads, runtime, ds.root)
    assert sorted(decoded) == sorted(r.image for r in test)
    assert out["gt"]["logic"][rec.image].extra == annotated.extra == out["gt"]["deepword"][rec.image].extra
    assert record_facing(out["detected"]["deepword"][rec.image]) == pytest.approx(
        record_facing(runtime.annotate(moved[rec.image], rgb)))
    (tmp_path / BUNDLE_FILE).write_text(json.dumps({"facing": None}))
    assert OnnxFacing.from_bundle(tmp_path) is None


def _relabelled(rendered: Path, root: Path, change) -> Path:
    """A copy of the rendered dataset with ``change(record)`` applied to every record (images copied)."""
    from deepword.word_format import read_records

    records = [change(r) for r in read_records(rendered / "labels.jsonl")]
    for r in records:
        (root / r.image).parent.mkdir(parents=True, exist_ok=True)
        (root / r.image).write_bytes((rendered / r.image).read_bytes())
    write_records(root / "labels.jsonl", records)
    write_dataset_index(root, root, json.loads((rendered / "splits.json").read_text()))
    return root


def _labelled_in_2d(rec):
    return replace(rec, extra={})


def test_without_3d_truth_or_roles_there_is_no_network_and_nothing_is_shipped(rendered, tmp_path):
    from stages.facing.stage import load_network

    flat_root = _relabelled(rendered, tmp_path / "flat",
                            lambda r: replace(r, extra={}, relations=[(v, w, None) for v, w, _ in r.relations]))
    out = tmp_path / "facing"
    out.mkdir()
    assert run_facing(_stage_cfg(), {"data": flat_root}, out) == {"facing.trained": 0.0}
    meta = json.loads((out / CONFIG_FILE).read_text())
    assert not meta["trained"] and "3D truth" in meta["reason"] and "rear" in meta["reason"]
    assert not (out / WEIGHTS_FILE).exists()
    assert load_network(out)[0] is None          # what the export stage checks: nothing to ship
    # the same with the roles, but told not to learn from them
    again = tmp_path / "again"
    again.mkdir()
    roles_kept = _relabelled(rendered, tmp_path / "roles", _labelled_in_2d)
    no_roles = {"objects_3d": True, "roles": False, "roles_only": []}
    assert run_facing(_stage_cfg(targets=no_roles), {"data": roles_kept}, again) == {"facing.trained": 0.0}


def test_a_couple_labelled_rear_and_front_points_from_its_rear_wheel_to_its_front_one():
    from deepword.word_format import Record
    from stages.facing.targets import role_facings

    boxes = np.array([[0, 0, 100, 50, 1, 0, 0], [10, 40, 20, 50, 1, 1, 1], [80, 38, 90, 48, 1, 1, 2],
                      [200, 0, 260, 40, 1, 0, 3], [210, 30, 220, 40, 1, 1, 4]], dtype=float)

    def rec(relations, pairs):
        return Record("a.png", 0, "front", 320, 240, boxes, relations, pairs)

    both = rec([(0, 1, "rear"), (0, 2, "front"), (3, 4, "front")], [(1, 2)])
    got = role_facings(both)
    assert got[0] == pytest.approx(np.array([70.0, -2.0]) / np.hypot(70.0, 2.0))
    assert np.isnan(got[1:]).all()                                  # wheels, and a vehicle with one wheel
    swapped = role_facings(rec([(0, 1, "front"), (0, 2, "rear")], [(1, 2)]))
    assert swapped[0] == pytest.approx(-got[0])
    assert np.isnan(role_facings(rec([(0, 1, "rear"), (0, 2, "front")], [])) ).all()     # not a couple
    assert np.isnan(role_facings(rec([(0, 1, None), (0, 2, None)], [(1, 2)]))).all()    # no roles labelled


def test_role_targets_point_the_way_the_3d_truth_does(rendered):
    from deepword.word_format import read_records
    from stages.facing.targets import facing_targets, role_facings

    records = read_records(rendered / "labels.jsonl")
    dots = []
    for r in records:
        truth, roles = box_facings(r), role_facings(r)
        both = np.isfinite(truth).all(axis=1) & np.isfinite(roles).all(axis=1)
        dots += list((truth[both] * roles[both]).sum(axis=1))
        assert np.array_equal(facing_targets(r), truth, equal_nan=True)             # 3D truth first
        flat = _labelled_in_2d(r)
        assert np.array_equal(facing_targets(flat), roles, equal_nan=True)          # else the roles
        pool = replace(r, extra={**r.extra, "data_source": "pool"})
        assert np.array_equal(facing_targets(pool, roles_only=["pool"]), roles, equal_nan=True)
        assert np.array_equal(facing_targets(pool, roles_only=["yours"]), truth, equal_nan=True)
        assert np.isnan(facing_targets(flat, roles=False)).all()
    assert len(dots) >= 5 and min(dots) > 0.5


def test_without_3d_truth_the_couples_roles_train_it(rendered, tmp_path):
    flat_root = _relabelled(rendered, tmp_path / "flat", _labelled_in_2d)
    out = tmp_path / "facing"
    out.mkdir()
    metrics = run_facing(_stage_cfg(), {"data": flat_root}, out)
    meta = json.loads((out / CONFIG_FILE).read_text())
    assert metrics["facing.trained"] == 1.0 and meta["trained"] and (out / WEIGHTS_FILE).is_file()
    assert meta["target_sources"]["train"]["objects_3d"] == 0 < meta["target_sources"]["train"]["roles"]
    assert metrics["facing.train.targets_roles"] == meta["target_sources"]["train"]["roles"]
    assert metrics["facing.val.vehicles"] == meta["target_sources"]["val"]["roles"]


def test_learning_from_nothing_is_refused_before_any_crop_is_cut(rendered, tmp_path, monkeypatch):
    import stages.facing.stage as facing_stage

    monkeypatch.setattr(facing_stage, "split_crops", lambda *a, **k: pytest.fail("crops cut"))
    nothing = {"objects_3d": False, "roles": False, "roles_only": []}
    with pytest.raises(ValueError, match=r"facing.targets: objects_3d and roles are both false"):
        run_facing(_stage_cfg(targets=nothing), {"data": rendered}, tmp_path)
