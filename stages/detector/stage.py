"""The ``detector`` DAG node: train CenterNet on the dataset's train split, keep the best epoch by val AP@0.5,
report COCO AP per class on val and test, and write WORD-format predictions for both.

Outputs (paths relative to the stage directory):
  model.pt, model.json            best weights (state_dict) and what rebuilds/preprocesses the model
  predictions_{val,test}.jsonl    detections in WORD format, original image coordinates, real scores
  checkpoints/                    Lightning checkpoints (best.ckpt, last.ckpt)
  logs/metrics.csv                training curves (also in the stage's MLflow run when tracked)
  artifacts/detections_test.png   detections drawn on test images; artifacts/curves.png
  artifacts/misses_test.md        recall by box size, occlusion and border truncation (stages/detector/misses.py)
                                  and what each kind of false positive costs AP@0.5 (deepword/detection/ap_errors.py)
  metrics.json                    the metrics returned to the engine
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from deepword.detection.ap_errors import ap_error_breakdown, append_breakdown, error_metrics
from deepword.detection.average_precision import coco_average_precision
from deepword.word_format import CLASS_NAMES, open_dataset, write_records
from pipeline.tracking import stage_run_info
from stages.detector.curves import plot_curves
from stages.detector.misses import breakdown_metrics, recall_breakdown, write_breakdown
from stages.detector.predict import predict_records
from stages.detector.render import write_detection_grid
from stages.detector.warm_start import fine_tuning, load_start
from stages.training.checkpoints import best_and_latest, weight_averaging
from stages.training.init_source import INIT_INPUT
from stages.training.loader_workers import loader_workers, usable_cores
from stages.training.memory_format import use_channels_last
from stages.training.precision import BF16, resolve_precision, trains_on_gpu
from stages.training.replicas import check_replicas_agree


def _loggers(out_dir: Path) -> list:
    from lightning.pytorch.loggers import CSVLogger, MLFlowLogger


    loggers = [CSVLogger(out_dir, name="logs", version="")]
    info = stage_run_info()
    if info is not None:
        uri, run_id = info
        loggers.append(MLFlowLogger(tracking_uri=uri, run_id=run_id))
    return loggers


def _threads(trainer_cfg: dict) -> int:
    """Intra-op threads: the trainer config's ``threads`` if set, else every core this process may use."""

    return int(trainer_cfg.get("threads") or usable_cores())


def _load_best_weights(net, checkpoint_path: str) -> None:
    import torch

    state = torch.load(checkpoint_path, map_location="cpu", weights_only=True)["state_dict"]
    net.load_state_dict({k.removeprefix("net."): v for k, v in state.items() if k.startswith("net.")})


def ap_metrics(predictions: list, truth: list, split: str, min_box_px: float) -> dict[str, float]:
    """``detector.<split>.{ap50,ap}.<class>`` with ground truth under ``min_box_px`` ignored, and, when that
    ignores anything, ``detector.<split>.{ap50_all,ap_all}.<class>`` over every box."""

    protocols = {"": min_box_px} if min_box_px <= 0 else {"": min_box_px, "_all": 0.0}
    out = {}
    for suffix, min_px in protocols.items():
        for name, ap in coco_average_precision(predictions, truth, CLASS_NAMES, min_px).items():
            for kind in ("ap50", "ap"):
                if not math.isnan(ap[kind]):
                    out[f"detector.{split}.{kind}{suffix}.{name}"] = ap[kind]
    return out


def check_crop(crop: list[int] | None, multiple: int) -> None:
    """Training crops pass through the same strides as whole inputs: their sides must divide evenly too."""
    if crop and any(int(side) % multiple for side in crop):
        raise ValueError(f"detector.augment.crop={list(crop)} must be divisible by {multiple} for this backbone")


def run(cfg: DictConfig, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    import lightning as L
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.detector.lightning import CenterNetModule, CloseMosaic, DetectorDataModule
    from stages.detector.model import build_centernet, model_config, save_detector
    from stages.training.lightning_logs import lightning_progress, route_lightning_logs

    route_lightning_logs()
    out_dir = Path(out_dir)
    det = OmegaConf.to_container(cfg.detector, resolve=True)
    if "init" in cfg:  # starts from earlier weights (init=run|checkpoints): the fine-tuning budget replaces epochs, lr
        det = fine_tuning(det, OmegaConf.to_container(cfg.init.train, resolve=True))
    trainer_cfg = OmegaConf.to_container(cfg.trainer, resolve=True) if "trainer" in cfg else {}
    L.seed_everything(int(cfg.seed if det.get("seed") is None else det["seed"]), workers=True)
    torch.set_num_threads(_threads(trainer_cfg))

    dataset = open_dataset(inputs["data"])
    splits = {name: dataset.subset(name) for name in ("train", "val", "test")}
    mcfg = model_config(det)
    precision = resolve_precision(trainer_cfg.get("precision", "32-true"), trainer_cfg.get("accelerator", "auto"))
    channels_last = use_channels_last(bool(det["channels_last"]), lambda: build_centernet(mcfg), precision == BF16,
                                      trains_on_gpu(trainer_cfg.get("accelerator", "auto")), "the detector")
    module = CenterNetModule(mcfg, det["loss"], det["optimizer"], det["score_threshold"], det["ap_min_box_px"],
                             channels_last)
    if "init" in cfg:  # before training; a resumed attempt's last.ckpt below then replaces them
        load_start(module.net, inputs[INIT_INPUT])
        module.freeze(cfg.init.train.get("freeze") or [])
    check_crop(det["augment"].get("crop"), module.net.backbone.stride_multiple)
    workers = loader_workers(det["num_workers"], trainer_cfg.get("accelerator", "auto"))
    data = DetectorDataModule(dataset.root, splits["train"], splits["val"], mcfg["input_width"], mcfg["input_height"],
                              det["augment"], det["batch_size"], workers, det["min_overlap"], mcfg["regression"])
    checkpoint, latest = best_and_latest(out_dir / "checkpoints", "val/ap50", "max")
    loggers = _loggers(out_dir)
    for logger in loggers:  # the precision this machine trained in, beside the configured "auto"
        logger.log_hyperparams({"detector.precision": precision, "detector.channels_last": channels_last,
                                "detector.loader_workers": workers})
    trainer = L.Trainer(
        max_epochs=det["epochs"], limit_train_batches=det["limit_train_batches"],
        limit_val_batches=det["limit_val_batches"], check_val_every_n_epoch=det["val_every_n_epochs"],
        accelerator=trainer_cfg.get("accelerator", "auto"), devices=trainer_cfg.get("devices", "auto"),
        strategy=trainer_cfg.get("strategy", "auto"), num_nodes=trainer_cfg.get("num_nodes", 1),
        precision=precision, logger=loggers,
        callbacks=[*weight_averaging(float(det.get("ema_decay", 0.0)), multi_tensor=True), checkpoint, latest,
                   CloseMosaic(det["augment"].get("mosaic_close_epochs", 0)), *lightning_progress("detector")],
        default_root_dir=out_dir, enable_progress_bar=True, log_every_n_steps=det["log_every_n_steps"],
        num_sanity_val_steps=0)
    started = time.perf_counter()
    # After a crash the engine hands this stage the same work dir again: resume from its last checkpoint.
    last = out_dir / "checkpoints" / "last.ckpt"
    trainer.fit(module, datamodule=data, ckpt_path=last if last.is_file() else None, weights_only=True)
    train_seconds = time.perf_counter() - started
    if not last.is_file():
        # The latest-epoch callback saves after validation; fewer epochs than detector.val_every_n_epochs
        # validate never, and the trained weights would be lost.
        trainer.save_checkpoint(last)
    check_replicas_agree(module, "detector")
    if not trainer.is_global_zero:  # another rank of a DDP launch: rank 0 saves, predicts and reports
        return {}

    net = build_centernet(mcfg)
    _load_best_weights(net, checkpoint.best_model_path or str(last))
    save_detector(out_dir, net, mcfg)
    # predict where it trained: on a GPU the val and test splits' fp32 forward passes take seconds, not minutes
    net.to(trainer.strategy.root_device)

    # images per second of the whole fit (validation epochs included): what an epoch budget is derived from
    train_images = trainer.global_step * det["batch_size"]
    metrics = {"detector.train_seconds": train_seconds, "detector.epochs": float(trainer.current_epoch),
               "detector.train_images_per_s": train_images / max(train_seconds, 1e-9),
               "detector.bf16": float(precision == BF16)}
    predictions = {}
    for split in ("val", "test"):
        preds = predict_records(net, dataset.root, splits[split], mcfg["input_width"], mcfg["input_height"],
                                mcfg["max_detections"], mcfg["score_threshold"], det["batch_size"])
        write_records(out_dir / f"predictions_{split}.jsonl", preds)
        predictions[split] = preds
        metrics |= ap_metrics(preds, splits[split], split, det["ap_min_box_px"])

    artifacts = out_dir / "artifacts"
    misses = recall_breakdown(splits["test"], predictions["test"], mcfg["class_names"], det["render_min_score"])
    write_breakdown(artifacts / "misses_test.md", misses, det["render_min_score"], "test")
    metrics |= breakdown_metrics(misses, "test")
    errors = ap_error_breakdown(splits["test"], predictions["test"], mcfg["class_names"], det["ap_min_box_px"])
    append_breakdown(artifacts / "misses_test.md", errors, "test split", det["ap_min_box_px"])
    metrics |= error_metrics(errors, "test")
    shown = slice(0, det["render_images"])
    write_detection_grid(artifacts / "detections_test.png", dataset.root, predictions["test"][shown],
                         splits["test"][shown], min_score=det["render_min_score"])
    if (out_dir / "logs" / "metrics.csv").is_file():
        plot_curves(out_dir / "logs" / "metrics.csv", artifacts / "curves.png")
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics
