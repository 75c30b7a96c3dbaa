"""The training stages' plan-time probes (stages/estimate/__init__.py) on the smoke profile's sizes."""

import math

import pytest
from hydra import compose, initialize_config_dir

import stages.estimate as estimate
from tests.pipeline.test_runmode import CONF


def _cfg(*overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose(config_name="config", overrides=["profile=smoke", "trainer.threads=1", *overrides])


@pytest.mark.parametrize("stage", ["detector", "relation", "facing"])
def test_a_real_probe_times_steps_and_says_how(stage):
    out = getattr(estimate, stage)(_cfg())
    assert math.isfinite(out["seconds"]) and out["seconds"] > 0
    assert "epochs" in out["note"] and "threads" in out["note"] and "epochs" in out["hint"]


def test_the_generators_stages_are_estimated_from_rendered_frames():
    cfg = _cfg("data.workers=2", "shift.data.frames=6")
    out = estimate.data(cfg)
    frames = int(cfg.data.frames)
    assert math.isfinite(out["seconds"]) and out["seconds"] > 0
    assert out["note"].startswith(f"{frames} frames x ") and out["note"].endswith("/ 2 processes")
    assert "data.frames=N" in out["hint"]
    held_out = estimate.shift_data(cfg)
    assert held_out["note"].startswith("6 frames x ") and "shift.data.frames=N" in held_out["hint"]
    # a dataset read from disk, or composed of sources, is not rendered: no estimate
    assert estimate.data(_cfg("data=word", "data.root=/nowhere")) is None


def test_the_estimate_is_steps_times_the_probed_step(monkeypatch):
    monkeypatch.setattr(estimate, "timed_steps", lambda step, sync=None: 0.5)  # every step and forward: 0.5 s
    monkeypatch.setattr(estimate, "_EPOCH_PROBES", {})   # no probe remembered from a real one
    cfg = _cfg("detector.epochs=4", "detector.val_every_n_epochs=2", "detector.limit_train_batches=1.0",
               "detector.limit_val_batches=1.0", "detector.batch_size=4")
    train = estimate.split_images(cfg, "train")
    val = estimate.split_images(cfg, "val")
    assert train == round(8 * 0.7) * 4 and val == round(8 * 0.1) * 4   # smoke: 8 frames x 4 cameras
    # a train step: the probed step (0.5 s) + loading its batch (4 items at 0.5 s / 4 each: the items are timed a
    # batch at a time), no loader workers on the CPU
    assert estimate.detector(cfg)["seconds"] == pytest.approx(4 * (train // 4) * 1.0 + 2 * math.ceil(val / 4) * 0.5)
    rel = _cfg("relation.ensemble=3", "relation.train.epochs=2", "relation.train.limit_train_images=null",
               "relation.train.limit_val_images=null", "relation.train.batch_size=8", "relation.distill.enabled=false")
    steps = math.ceil(train * 2 / 8)  # each train image twice: once as annotated, once as a detector might see it
    # a train step: the probed step (0.5 s) + the crops' augmentation of its batch (0.5 s: timed a batch at a time)
    assert estimate.relation(rel)["seconds"] == pytest.approx(3 * 2 * (2 * steps + math.ceil(val / 8)) * 0.5)
    assert "augmentation" in estimate.relation(rel)["note"]
    plain = _cfg("relation.ensemble=3", "relation.train.epochs=2", "relation.train.limit_train_images=null",
                 "relation.train.limit_val_images=null", "relation.train.batch_size=8", "relation.augment.prob=0",
                 "relation.distill.enabled=false")
    assert estimate.relation(plain)["seconds"] == pytest.approx(3 * 2 * (steps + math.ceil(val / 8)) * 0.5)
    assert "augmentation" not in estimate.relation(plain)["note"]
    # relation.distill: a student after the members, its steps also running the three members forward (3 x 0.5 s)
    taught = _cfg("relation.ensemble=3", "relation.train.epochs=2", "relation.train.limit_train_images=null",
                  "relation.train.limit_val_images=null", "relation.train.batch_size=8", "relation.augment.prob=0",
                  "relation.distill.enabled=true")
    epoch = (steps + math.ceil(val / 8)) * 0.5
    assert estimate.relation(taught)["seconds"] == pytest.approx(3 * 2 * epoch + 2 * (epoch + steps * 3 * 0.5))
    assert "student" in estimate.relation(taught)["note"]
    # early stopping: the epochs to the usual best plus the patience a network, the configured epochs at most
    stopping = _cfg("relation.ensemble=1", "relation.train.epochs=30", "relation.train.patience=3",
                    "relation.train.limit_train_images=null", "relation.train.limit_val_images=null",
                    "relation.train.batch_size=8", "relation.augment.prob=0")
    expected = estimate.RELATION_BEST_EPOCH + 3
    assert estimate.relation(stopping)["seconds"] == pytest.approx(expected * (steps + math.ceil(val / 8)) * 0.5)
    assert f"~{expected} of 30 epochs" in estimate.relation(stopping)["note"]
    short = _cfg("relation.ensemble=1", "relation.train.epochs=7", "relation.train.patience=3",
                 "relation.train.limit_train_images=null", "relation.train.limit_val_images=null",
                 "relation.train.batch_size=8", "relation.augment.prob=0")
    assert estimate.relation(short)["seconds"] == pytest.approx(7 * (steps + math.ceil(val / 8)) * 0.5)
    fac = _cfg("facing.train.epochs=3", "facing.train.batch_size=16")
    crops, val_crops = train * estimate.MEAN_OBJECTS * estimate.VEHICLE_SHARE, val * estimate.MEAN_OBJECTS / 3
    # every train vehicle twice (as labelled and jittered); val flip-averaged: two forward passes a batch
    want = 3 * (math.ceil(2 * crops / 16) + 2 * math.ceil(val_crops / 16)) * 0.5
    assert estimate.facing(fac)["seconds"] == pytest.approx(want)


def test_no_frames_no_estimate():
    assert estimate.split_images(_cfg("data=word", "data.root=/nonexistent"), "train") is None
    assert estimate.limited_batches(100, 8, 3) == 3 and estimate.limited_batches(100, 8, 0.5) == 6


def test_auto_epochs_fill_the_minutes_within_the_bounds(monkeypatch):
    # 30 s an epoch of training + a 20 s validation every 5 epochs: 34 s an epoch
    monkeypatch.setattr(estimate, "detector_epoch", lambda cfg: {"epoch_s": 30.0, "validation_s": 20.0, "how": "toy"})
    auto = ["detector.epochs=auto", "detector.val_every_n_epochs=5", "detector.sizing.min_epochs=10",
            "detector.sizing.max_epochs=55"]
    out = estimate.detector_epochs(_cfg(*auto, "detector.sizing.minutes=15"))
    assert out["config"] == {"detector.epochs": 26} and "fit 15 min at ~34 s an epoch: toy" in out["note"]
    out = estimate.detector_epochs(_cfg(*auto, "detector.sizing.minutes=60"))
    assert out["config"] == {"detector.epochs": 55} and "the most" in out["note"]
    out = estimate.detector_epochs(_cfg(*auto, "detector.sizing.minutes=1"))
    assert out["config"] == {"detector.epochs": 10} and "over the budget" in out["note"]
    assert estimate.detector_epochs(_cfg("detector.epochs=7")) is None, "a number is left as given"
    monkeypatch.undo()   # the real probe: it has no image count to time an epoch by
    no_count = estimate.detector_epochs(_cfg(*auto, "detector.sizing.minutes=15", "data=word", "data.root=/nonexistent"))
    assert no_count["config"] == {"detector.epochs": 55} and "no image count" in no_count["note"]
    with pytest.raises(ValueError, match="min_epochs <= max_epochs"):
        estimate.detector_epochs(_cfg(*auto, "detector.sizing.minutes=15", "detector.sizing.min_epochs=60"))


def test_the_loader_probe_runs_the_training_items_on_synthetic_images():
    seconds = estimate._loader_item_seconds(_cfg(), dict(_cfg().detector))
    assert 0 < seconds < 5


def test_the_sizing_and_the_estimate_of_one_plan_share_one_probe(monkeypatch):
    calls = []
    monkeypatch.setattr(estimate, "_EPOCH_PROBES", {})
    monkeypatch.setattr(estimate, "_probe_detector_epoch",
                        lambda cfg: calls.append(1) or {"epoch_s": 10.0, "validation_s": 5.0, "how": "toy"})
    auto = _cfg("detector.epochs=auto", "detector.sizing.minutes=1", "detector.sizing.min_epochs=1")
    sized = estimate.detector_epochs(auto)["config"]["detector.epochs"]
    estimate.detector(_cfg(f"detector.epochs={sized}"))
    assert len(calls) == 1
    estimate.detector(_cfg(f"detector.epochs={sized}", "detector.batch_size=2"))
    assert len(calls) == 2, "another configuration: probed again"
