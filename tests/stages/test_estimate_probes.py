"""The training stages' plan-time probes (stages/estimate/__init__.py) on the smoke profile's sizes."""

import math

import pytest
from hydra import compose, initialize_config_dir

import stages.estimate as estimate
import stages.estimate.after_training as after_training
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


@pytest.mark.parametrize("stage", ["priors", "export", "evaluate", "bev"])
def test_the_stages_after_training_are_estimated_from_calls_timed_here(stage):
    out = getattr(after_training, stage)(_cfg())
    assert math.isfinite(out["seconds"]) and out["seconds"] > 0
    assert out["note"] and out["hint"]


def test_the_stages_after_training_count_the_calls_they_make(monkeypatch):
    units = {"threads": 2, "relation": 0.001, "relation_eager": 0.004, "relation_export": 1.0, "detector": 0.01,
             "detector_eager": 0.02, "detector_export": 0.5, "decode": 0.003}
    monkeypatch.setattr(after_training, "unit_calls", lambda cfg: units)
    flip = "relation.decode.flip_average=true"  # each image and its mirror: two relation calls a row
    cfg = _cfg("eval.fit_images=10", flip)
    test, train = estimate.split_images(cfg, "test"), estimate.split_images(cfg, "train")
    held_out = int(cfg.shift.data.frames) * 4
    # every test image of both domains: the detector, the relation model for 2 box sources x 2 rows (deepword and
    # its INT8 twin) on the image and its mirror, three reads, the scoring; the baselines fitted on 10 train images
    per_image = 0.01 + 2 * 2 * (2 * 0.001 + after_training.GRAPH_S) + 3 * 0.003 + after_training.EVAL_OTHER_PER_IMAGE_S
    fit = min(10, train) * after_training.EVAL_FIT_PER_TRAIN_IMAGE_S
    assert after_training.evaluate(cfg)["seconds"] == pytest.approx(fit + (test + held_out) * per_image)
    once = after_training.evaluate(_cfg("eval.fit_images=10", "relation.decode.flip_average=false"))["seconds"]
    assert once == pytest.approx(fit + (test + held_out) * (per_image - 2 * 2 * 0.001))  # each image scored once
    in_domain = after_training.evaluate(_cfg("eval.fit_images=10", "pipeline.skip=[shift_data]", flip))["seconds"]
    assert in_domain == pytest.approx(fit + test * per_image)
    # without a detector: no detected boxes, so neither the detector's calls nor that source's relation calls
    no_detector = after_training.evaluate(_cfg("eval.fit_images=10", "pipeline.skip=[detector]", flip))["seconds"]
    per_image_gt = 2 * (2 * 0.001 + after_training.GRAPH_S) + 3 * 0.003 + after_training.EVAL_OTHER_PER_IMAGE_S
    assert no_detector == pytest.approx(fit + (test + held_out) * per_image_gt)

    # export: the latency tables grow with their runs; without a detector no operating point is searched
    runs = [after_training.export(_cfg(f"export.latency.runs={n}", "export.latency.warmup=0"))["seconds"]
            for n in (10, 20)]
    relation_row = after_training.LATENCY_RELATION_CALLS * 0.001 + after_training.LATENCY_RELATION_EAGER_CALLS * 0.004
    assert runs[1] - runs[0] == pytest.approx(10 * (relation_row + 11 * 0.01 + 0.02))
    with_detector = after_training.export(cfg)
    without = after_training.export(_cfg("pipeline.skip=[detector]"))
    assert "operating point" in with_detector["note"] and "operating point" not in without["note"]
    assert without["seconds"] < with_detector["seconds"]
    # where the detector is skipped its calls are not timed at all (the ten-dataset sweep): an estimate all the same
    monkeypatch.setattr(after_training, "unit_calls",
                        lambda cfg: {k: v for k, v in units.items() if not k.startswith("detector")})
    relation_only = after_training.export(_cfg("pipeline.skip=[detector]"))
    assert relation_only["seconds"] == pytest.approx(without["seconds"] - 2 * 0.5)   # no detector export either
    assert "detector" not in relation_only["note"] and "relation 1.00 ms" in relation_only["note"]

    # bev: the fits shared among processes, at most one per FRAMES_PER_TASK frames
    monkeypatch.setattr(after_training, "_no_wheel_fit_seconds", lambda cfg: 0.5)
    monkeypatch.setattr(after_training, "decode_seconds", lambda cfg: 0.003)
    big = ("data.frames=200", "shift.data.frames=100")
    one, two = (after_training.bev(_cfg(*big, f"bev.workers={w}", "pipeline.skip=[shift_data]"))["seconds"]
                for w in (1, 2))
    fits_one = estimate.split_images(_cfg(*big), "test") * 2 * after_training.FITS_PER_IMAGE * 0.5
    assert one - two == pytest.approx(fits_one / 2 - after_training.PROCESS_START_S)
    smoke_two = after_training.bev(_cfg("bev.workers=2", "pipeline.skip=[shift_data]"))["seconds"]
    smoke_one = after_training.bev(_cfg("bev.workers=1", "pipeline.skip=[shift_data]"))["seconds"]
    assert smoke_two == pytest.approx(smoke_one), "a smoke test split of a few frames is fitted in one process"
