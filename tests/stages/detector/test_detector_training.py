import json
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from deepword.word_format import open_dataset, read_records
from stages.detector.lightning import (
    CenterNetModule,
    DetectorDataModule,
    NonFiniteLossError,
    check_finite_loss,
)
from stages.detector.model import load_detector, model_config

CONF = Path(__file__).resolve().parents[3] / "conf"


def detector_cfg(**overrides) -> dict:
    """The real detector config files, shrunk for the toy dataset (128 x 96 images)."""
    cfg = OmegaConf.load(CONF / "detector" / "default.yaml")
    cfg.merge_with(OmegaConf.load(CONF / "detector" / "backbone" / "tiny.yaml"))   # @package detector: backbone, head_conv
    cfg.merge_with({"input_width": 128, "input_height": 96, "batch_size": 4, "epochs": 1, "render_images": 2,
                    "ap_min_box_px": 7,  # ignores the toy's smallest (6 px) wheels
                    "log_every_n_steps": 1, "backbone": {"channels": [8, 16, 16, 32], "blocks": [1, 1, 1], "out_channels": 16},
                    "head_conv": 16})
    cfg.merge_with(overrides)
    return OmegaConf.to_container(cfg, resolve=True)


def test_fast_dev_run(toy_dataset, tmp_path):
    det = detector_cfg()
    ds = open_dataset(toy_dataset)
    module = CenterNetModule(model_config(det), det["loss"], det["optimizer"], det["score_threshold"])
    data = DetectorDataModule(ds.root, ds.subset("train"), ds.subset("val"), det["input_width"], det["input_height"],
                              det["augment"], det["batch_size"], 0, det["min_overlap"], det["regression"])
    batch = next(iter(data.train_dataloader()))
    assert batch["image"].shape == (4, 96, 128, 3) and batch["hm"].shape == (4, 2, 24, 32)
    assert batch["mask"].sum() >= 4 * 3  # every toy image has a vehicle and two wheels
    trainer = L.Trainer(fast_dev_run=True, accelerator="cpu", logger=False, enable_progress_bar=False,
                        default_root_dir=tmp_path)
    trainer.fit(module, datamodule=data)
    assert np.isfinite(trainer.callback_metrics["train/loss_step"].item())
    assert "val/ap50" in trainer.callback_metrics and "val/ap50.wheel" in trainer.callback_metrics


def test_non_finite_loss_stops_with_a_clear_message():
    with pytest.raises(NonFiniteLossError, match="non-finite training loss nan at epoch 3, step 7"):
        check_finite_loss(torch.tensor(float("nan")), {"hm": torch.tensor(float("nan"))}, 3, 7)
    check_finite_loss(torch.tensor(1.5), {}, 0, 0)


def test_empty_val_split_is_an_error(toy_dataset):
    ds = open_dataset(toy_dataset)
    with pytest.raises(ValueError, match="val split is empty"):
        DetectorDataModule(ds.root, ds.subset("train"), [], 128, 96, None, 4, 0, 0.7, "ttfnet")


@pytest.mark.parametrize("native_bf16", [True, False], ids=["bf16", "fp32-fallback"])
def test_stage_run_on_a_toy_dataset(toy_dataset, tmp_path, monkeypatch, native_bf16):
    from stages.detector.stage import run
    from stages.training import precision

    # trainer.precision auto: bf16 with channels_last where the CPU has native bf16, fp32 elsewhere (NCHW here: the
    # toy backbone's 8-channel stem feeds a strided 1x1 shortcut, stages/training/memory_format.py)
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: native_bf16)
    cfg = OmegaConf.create({"detector": detector_cfg(epochs=2, augment={"crop": [64, 64]}), "seed": 3,
                            "trainer": OmegaConf.load(CONF / "trainer" / "cpu.yaml")})
    cfg.trainer.threads = 1
    out = tmp_path / "detector"
    out.mkdir()
    metrics = run(cfg, {"data": toy_dataset}, out)

    for split in ("val", "test"):
        for kind in ("ap50", "ap"):
            for name in ("vehicle", "wheel"):
                assert 0.0 <= metrics[f"detector.{split}.{kind}.{name}"] <= 100.0
                assert 0.0 <= metrics[f"detector.{split}.{kind}_all.{name}"] <= 100.0
    assert json.loads((out / "metrics.json").read_text()) == metrics
    assert metrics["detector.bf16"] == float(native_bf16) and metrics["detector.train_images_per_s"] > 0
    if not native_bf16:
        return  # the rest does not depend on the precision
    ds = open_dataset(toy_dataset)
    for split in ("val", "test"):
        preds = read_records(out / f"predictions_{split}.jsonl", root=ds.root, allow_empty=True)
        truth = ds.subset(split)
        assert [p.image for p in preds] == [t.image for t in truth]
        for p in preds:
            assert p.relations == [] and len(set(p.box_ids)) == len(p.box_ids)
            assert np.all(p.scores >= 0.1) and np.all(p.xyxy >= 0)
            assert np.all(p.xyxy[:, [0, 2]] <= p.width) and np.all(p.xyxy[:, [1, 3]] <= p.height)
    assert (out / "checkpoints" / "last.ckpt").is_file() and (out / "checkpoints" / "best.ckpt").is_file()
    assert (out / "artifacts" / "detections_test.png").stat().st_size > 1000
    assert (out / "artifacts" / "curves.png").is_file()
    assert "## Where AP@0.5 goes (test split)" in (out / "artifacts" / "misses_test.md").read_text()
    for name in ("vehicle", "wheel"):
        assert metrics[f"detector.test.ap50_no_false_positives.{name}"] >= metrics[f"detector.test.ap50.{name}"]
    net, config = load_detector(out)
    assert config["input_width"] == 128 and not net.training


def test_crops_must_fit_the_backbone_strides(toy_dataset, tmp_path):
    from stages.detector.stage import run

    cfg = OmegaConf.create({"detector": detector_cfg(augment={"crop": [72, 64]}), "seed": 3, "trainer": {"threads": 1}})
    with pytest.raises(ValueError, match=r"detector.augment.crop=\[72, 64\] must be divisible by 16"):
        run(cfg, {"data": toy_dataset}, tmp_path)


def test_batch_normalisation_in_torch_equals_the_per_image_numpy_one():
    from deepword.detection.letterbox import normalise
    from stages.detector.lightning import batch_to_input

    images = np.random.default_rng(0).integers(0, 256, (3, 16, 24, 3), dtype=np.uint8)
    x = batch_to_input(torch.from_numpy(images), torch.channels_last)
    assert x.shape == (3, 3, 16, 24) and x.is_contiguous(memory_format=torch.channels_last)
    np.testing.assert_allclose(x.numpy(), np.stack([normalise(im) for im in images]), atol=1e-6)


def test_the_detector_seed_is_the_training_draw(toy_dataset, tmp_path, monkeypatch):
    """detector.seed null trains as the run's seed does; another detector.seed draws other weights from the same data."""
    from stages.detector.stage import run
    from stages.training import precision

    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: False)  # fp32: the quickest path here

    def weights(seed: int | None) -> dict:
        cfg = OmegaConf.create({"detector": detector_cfg(epochs=1, seed=seed, augment={"crop": [64, 64]}), "seed": 3,
                                "trainer": {"threads": 1, "precision": "32-true"}})
        out = tmp_path / f"seed_{seed}"
        out.mkdir()
        run(cfg, {"data": toy_dataset}, out)
        return load_detector(out)[0].state_dict()

    default, same, other = weights(None), weights(3), weights(4)
    assert all(torch.equal(default[k], same[k]) for k in default)
    assert not all(torch.equal(default[k], other[k]) for k in default)


def test_fewer_epochs_than_the_validation_interval_still_ship_the_trained_weights(toy_dataset, tmp_path):
    """No epoch validates, so no best checkpoint: the stage saves the latest one itself and ships it."""
    from stages.detector.stage import run

    cfg = OmegaConf.create({"detector": detector_cfg(epochs=1, val_every_n_epochs=2, augment={"crop": [64, 64]}),
                            "seed": 3, "trainer": OmegaConf.load(CONF / "trainer" / "cpu.yaml")})
    cfg.trainer.threads, cfg.trainer.precision = 1, "32-true"
    out = tmp_path / "detector"
    out.mkdir()
    metrics = run(cfg, {"data": toy_dataset}, out)

    assert metrics["detector.epochs"] == 1.0
    assert (out / "checkpoints" / "last.ckpt").is_file() and not (out / "checkpoints" / "best.ckpt").exists()
    shipped = torch.load(out / "model.pt", weights_only=True)
    last = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    assert all(torch.equal(shipped[k.removeprefix("net.")], v) for k, v in last.items() if k.startswith("net."))
