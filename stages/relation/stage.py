"""The `relation` stage: build (and cache) graph inputs, train the DeepWORD relation network with
Lightning, keep the best weights by val wheel_acc.

Outputs in the stage directory:
- ``relation.pt``   the best RelationNet state_dict (load with weights_only=True);
- ``relation.json`` what the predictor and the export stage need to rebuild it: model and input
                    config, decoding, whether roles were learned, seed, metrics;
- ``artifacts/relation_curves.png`` training curves (also in the stage's MLflow run when tracked).
While training, ``inputs/<split>.npz`` (cropped graphs) and ``checkpoints/`` (``last.ckpt`` for resuming)
live in the stage directory too; both are removed once the stage succeeds.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path

from stages.checkpoints import best_and_latest, weight_averaging
from stages.lightning_logs import lightning_progress, route_lightning_logs
from stages.precision import BF16, FP32, resolve_precision
from stages.relation.augment import AugmentConfig
from stages.relation.inputs import InputConfig, SplitInputs, build_split, check_object_counts
from stages.relation.simulate import DetectionNoise, with_simulated_detections
from stages.relation.warp import BoxWarpConfig
from stages.word_format import load_image, open_dataset

WEIGHTS_FILE = "relation.pt"
CONFIG_FILE = "relation.json"
MONITOR = "val/select"  # val wheel_acc, or minus the val loss (relation.train.select; lightning.RelationModule)


def _limit(records: list, limit) -> list:
    return records if limit is None else records[: int(limit)]


def split_inputs(name: str, records, root: Path, in_cfg: InputConfig, priors, cache_dir: Path,
                 min_box_px: float) -> SplitInputs:
    """A split's graphs, from ``cache_dir/<name>.npz`` when an interrupted run already built them."""
    path = cache_dir / f"{name}.npz"
    meta = cache_dir / f"{name}.json"
    key = json.dumps({"inputs": asdict(in_cfg), "min_box_px": min_box_px, "images": [r.image for r in records]},
                     sort_keys=True)
    if path.is_file() and meta.is_file() and meta.read_text() == key:
        return SplitInputs.load(path)
    split = build_split(records, lambda rec: load_image(root, rec), in_cfg, priors.wheel_vehicle, priors.wheel_wheel,
                        min_box_px)
    cache_dir.mkdir(parents=True, exist_ok=True)
    split.save(path)
    meta.write_text(key)
    return split


def _tracking_logger():
    """Lightning's MLFlowLogger attached to the stage's MLflow child run, or None outside the pipeline."""
    from pipeline.tracking import stage_run_info

    info = stage_run_info()
    if info is None:
        return None
    from lightning.pytorch.loggers import MLFlowLogger

    uri, run_id = info
    return MLFlowLogger(tracking_uri=uri, run_id=run_id, log_model=False)


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import EarlyStopping
    from omegaconf import OmegaConf

    from stages.priors.mixture import load_priors
    from stages.relation.curves import CurveHistory, plot_curves
    from stages.relation.lightning import RelationDataModule, RelationModule, score_split
    from stages.relation.model import ModelConfig, count_parameters, size_mb
    from stages.replicas import check_replicas_agree

    route_lightning_logs()
    started = time.perf_counter()
    out_dir = Path(out_dir)
    rel, tr = cfg.relation, cfg.trainer
    if int(rel.train.epochs) < 1:
        raise ValueError(f"relation.train.epochs must be >= 1, got {rel.train.epochs}")
    torch.set_num_threads(int(rel.train.threads))
    L.seed_everything(int(rel.train.seed), workers=True)

    ds = open_dataset(inputs["data"])
    priors = load_priors(inputs["priors"])
    in_cfg = InputConfig.from_cfg(rel)
    model_cfg = ModelConfig.from_cfg(rel)
    check_object_counts(ds.records, in_cfg.max_objects)  # every split: export uses the same padding
    cache_dir = out_dir / "inputs"
    min_box_px = float(rel.val_min_box_px)
    noise = DetectionNoise.from_cfg(rel.train.get("detection_noise"))
    train_records = with_simulated_detections(_limit(ds.subset("train"), rel.train.limit_train_images), noise,
                                              int(rel.train.seed), in_cfg.max_objects)
    train = split_inputs("train", train_records, ds.root, in_cfg, priors, cache_dir, min_box_px)
    val = split_inputs("val", _limit(ds.subset("val"), rel.train.limit_val_images), ds.root, in_cfg, priors,
                       cache_dir, min_box_px)
    if len(train) == 0 or len(val) == 0:
        raise ValueError(f"relation: need train and val images, got {len(train)} train and {len(val)} val")

    plain = OmegaConf.to_container(rel, resolve=True)
    precision = resolve_precision(tr.precision, tr.accelerator)
    backbone_bf16 = precision == BF16  # the module autocasts its backbone itself; the rest trains in fp32
    module = RelationModule(model=asdict(model_cfg), loss=plain["loss"], decode=plain["decode"],
                            optim={"lr": float(rel.train.lr), "weight_decay": float(rel.train.weight_decay)},
                            backbone_bf16=backbone_bf16, select=str(rel.train.get("select", "wheel_acc")))
    augment = AugmentConfig.from_cfg(plain.get("augment"))
    box_warp = BoxWarpConfig.from_cfg(plain.get("box_warp"))
    data = RelationDataModule(train, val, int(rel.train.batch_size), float(rel.train.hflip), augment, box_warp)
    ckpt_dir = out_dir / "checkpoints"
    checkpoint, latest = best_and_latest(ckpt_dir, MONITOR, "max")
    history = CurveHistory()
    callbacks = [checkpoint, latest, EarlyStopping(monitor=MONITOR, mode="max", patience=int(rel.train.patience)),
                 history, *lightning_progress("relation")]
    callbacks = [*weight_averaging(float(rel.train.get("ema_decay", 0.0))), *callbacks]
    logger = _tracking_logger()
    if logger is not None:  # the precision this machine trained in, beside the configured "auto"
        logger.log_hyperparams({"relation.precision": precision})
    trainer = L.Trainer(max_epochs=int(rel.train.epochs), accelerator=tr.accelerator, devices=tr.devices,
                        strategy=tr.strategy, num_nodes=int(tr.num_nodes), precision=FP32 if backbone_bf16 else precision,
                        logger=logger if logger is not None else False, callbacks=callbacks,
                        deterministic=True, default_root_dir=out_dir, log_every_n_steps=10,
                        enable_model_summary=False)
    last = ckpt_dir / "last.ckpt"
    trainer.fit(module, datamodule=data, ckpt_path=last if last.is_file() else None, weights_only=True)
    check_replicas_agree(module, "relation")
    if not trainer.is_global_zero:  # another rank of a DDP launch: rank 0 saves and reports
        return {}

    if not history.rows and last.is_file():  # ddp_spawn: the epochs ran in child processes
        history.load_state_dict(torch.load(last, map_location="cpu", weights_only=True)["callbacks"][history.state_key])
    best = torch.load(checkpoint.best_model_path or last, map_location="cpu", weights_only=True)
    module.load_state_dict(best["state_dict"])
    net = module.model.cpu().eval()
    val_metrics = score_split(module.cpu(), val, int(rel.train.batch_size))

    torch.save(net.state_dict(), out_dir / WEIGHTS_FILE)
    metrics = {"relation.params": float(count_parameters(net)), "relation.size_mb": size_mb(net),
               "relation.epochs": float(len(history.rows)), "relation.train.images": float(len(train)),
               "relation.train.seconds": time.perf_counter() - started, "relation.bf16": float(backbone_bf16)}
    metrics.update({f"relation.val.{k}": float(v) for k, v in val_metrics.items()})
    has_roles = bool((train.role >= 0).any())
    (out_dir / CONFIG_FILE).write_text(json.dumps({
        "model": asdict(model_cfg), "inputs": asdict(in_cfg), "decode": plain["decode"], "has_roles": has_roles,
        "seed": int(rel.train.seed), "best_epoch": int(best.get("epoch", -1)), "metrics": metrics,
        "curves": history.rows}, indent=1))
    plot_curves(history.rows, out_dir / "artifacts" / "relation_curves.png")
    shutil.rmtree(cache_dir, ignore_errors=True)  # re-croppable; would bloat the cache entry
    shutil.rmtree(ckpt_dir, ignore_errors=True)  # relation.pt holds the best weights
    return metrics


def load_network(stage_dir: str | os.PathLike):
    """The trained RelationNet (eval mode, CPU) and its relation.json."""
    import torch

    from stages.relation.model import ModelConfig, RelationNet

    stage_dir = Path(stage_dir)
    meta = json.loads((stage_dir / CONFIG_FILE).read_text())
    net = RelationNet(ModelConfig(**meta["model"]))
    net.load_state_dict(torch.load(stage_dir / WEIGHTS_FILE, map_location="cpu", weights_only=True))
    return net.eval(), meta
