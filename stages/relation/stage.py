"""The `relation` stage: build (and cache) graph inputs, train the DeepWORD relation network with
Lightning, keep the best weights by val wheel_acc.

Outputs in the stage directory:
- ``relation.pt``   the best RelationNet state_dict: the student the members teach (``relation.distill``), or the
                    RelationEnsemble's (``relation.ensemble`` > 1 without it: its members trained from consecutive
                    seeds); load with ``load_network``;
- ``relation.json`` what the predictor and the export stage need to rebuild it: model and input
                    config, decoding, whether roles were learned, seed, metrics;
- ``artifacts/relation_curves.png`` training curves of the first network (also in the stage's MLflow run when
                    tracked); ``artifacts/relation_student_curves.png`` the student's.
While training, ``inputs/<split>.npz`` (cropped graphs), ``checkpoints/`` (``last.ckpt`` for resuming) and, for an
ensemble, ``members/<k>/`` (each finished member, so an interrupted stage resumes after it) live in the stage
directory too; all are removed once the stage succeeds.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from deepword.priors import load_priors
from deepword.relation_graph import InputConfig, SplitInputs, build_split, check_object_counts
from deepword.word_format import load_image, open_dataset
from pipeline.tracking import stage_run_info
from stages.relation.augment import AugmentConfig
from stages.relation.distill import STUDENT, DistillConfig
from stages.relation.simulate import DetectionNoise, with_simulated_detections
from stages.relation.warm_start import fine_tuning, start_states
from stages.relation.warp import BoxWarpConfig
from stages.training.checkpoints import best_and_latest, weight_averaging
from stages.training.init_source import INIT_INPUT
from stages.training.lightning_logs import lightning_progress, route_lightning_logs
from stages.training.loader_workers import loader_workers
from stages.training.memory_format import use_channels_last
from stages.training.precision import BF16, FP32, resolve_precision, trains_on_gpu
from stages.training.replicas import check_replicas_agree

WEIGHTS_FILE = "relation.pt"
CONFIG_FILE = "relation.json"
MONITOR = "val/select"  # val wheel_acc, or minus the val loss (relation.train.select; lightning.RelationModule)


def _limit(records: list, limit) -> list:
    return records if limit is None else records[: int(limit)]


def split_inputs(name: str, records, root: Path, in_cfg: InputConfig, priors, cache_dir: Path,
                 min_box_px: float, threads: int = 1) -> SplitInputs:
    """A split's graphs, from ``cache_dir/<name>.npz`` when an interrupted run already built them; else built from
    the images, ``threads`` at a time."""
    path = cache_dir / f"{name}.npz"
    meta = cache_dir / f"{name}.json"
    key = json.dumps({"inputs": asdict(in_cfg), "min_box_px": min_box_px, "images": [r.image for r in records]},
                     sort_keys=True)
    if path.is_file() and meta.is_file() and meta.read_text() == key:
        return SplitInputs.load(path)
    split = build_split(records, lambda rec: load_image(root, rec), in_cfg, priors.wheel_vehicle, priors.wheel_wheel,
                        min_box_px, threads)
    cache_dir.mkdir(parents=True, exist_ok=True)
    split.save(path)
    meta.write_text(key)
    return split


def _tracking_logger():
    """Lightning's MLFlowLogger attached to the stage's MLflow child run, or None outside the pipeline."""

    info = stage_run_info()
    if info is None:
        return None
    from lightning.pytorch.loggers import MLFlowLogger

    uri, run_id = info
    return MLFlowLogger(tracking_uri=uri, run_id=run_id, log_model=False)


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.relation.curves import plot_curves
    from stages.relation.lightning import score_split
    from stages.relation.model import ModelConfig, RelationEnsemble, count_parameters, size_mb

    route_lightning_logs()
    started = time.perf_counter()
    out_dir = Path(out_dir)
    if "init" in cfg:  # starts from earlier weights (init=run|checkpoints): the fine-tuning budget replaces relation.train's
        cfg = fine_tuning(cfg, cfg.init.train)
    rel = cfg.relation
    if int(rel.train.epochs) < 1:
        raise ValueError(f"relation.train.epochs must be >= 1, got {rel.train.epochs}")
    n_members = int(rel.get("ensemble", 1))
    if n_members < 1:
        raise ValueError(f"relation.ensemble must be >= 1 (the number of networks), got {n_members}")
    torch.set_num_threads(int(rel.train.threads))

    ds = open_dataset(inputs["data"])
    priors = load_priors(inputs["priors"])
    in_cfg = InputConfig.from_cfg(rel)
    model_cfg = ModelConfig.from_cfg(rel)
    check_object_counts(ds.records, in_cfg.max_objects)  # every split: export uses the same padding
    cache_dir = out_dir / "inputs"
    min_box_px = float(rel.val_min_box_px)
    val = split_inputs("val", _limit(ds.subset("val"), rel.train.limit_val_images), ds.root, in_cfg, priors,
                       cache_dir, min_box_px, int(rel.train.threads))
    seeds = [int(rel.train.seed) + k for k in range(n_members)]
    starts = start_states(inputs[INIT_INPUT], n_members) if "init" in cfg else [None] * n_members
    members = [train_member(cfg, ds, priors, in_cfg, model_cfg, val, seed, out_dir, k if n_members > 1 else None,
                            starts[k])
               for k, seed in enumerate(seeds)]
    distill = DistillConfig.from_cfg(rel.get("distill"))
    taught = distill.ships_student(n_members)  # one network taught by the members ships in their place
    if members[0] is None and not taught:  # another rank of a DDP launch: rank 0 saves and reports
        return {}
    student = None
    if taught:
        teachers = teachers_on_every_rank(members)  # every rank of a DDP launch trains the student
        teachers_val = score_split(teachers, val, int(rel.train.batch_size)) if members[0] is not None else {}
        # fine-tuning (init): the student starts where the members did, from the earlier run's weights
        start = starts[0] if "init" in cfg else teachers[0].model.state_dict() if distill.start == "member" else None
        student = train_member(cfg, ds, priors, in_cfg, model_cfg, val, seeds[-1] + 1, out_dir, STUDENT, start,
                               teachers=teachers)
        if student is None:
            return {}
    modules = [student.module] if student is not None else [m.module for m in members]  # on the CPU (train_member)
    nets = [m.model.eval() for m in modules]
    net = nets[0] if len(nets) == 1 else RelationEnsemble(nets).eval()
    val_metrics = score_split(modules, val, int(rel.train.batch_size))

    torch.save(net.state_dict(), out_dir / WEIGHTS_FILE)
    history, best_epoch = members[0].history, members[0].best_epoch
    metrics = {"relation.params": float(count_parameters(net)), "relation.size_mb": size_mb(net),
               "relation.epochs": float(len(history)), "relation.train.images": float(members[0].train_images),
               "relation.train.seconds": time.perf_counter() - started, "relation.bf16": float(members[0].bf16),
               "relation.ensemble": float(n_members)}
    metrics.update({f"relation.val.{k}": float(v) for k, v in val_metrics.items()})
    headline = ("wheel_acc", "image_acc", "pair_f1")
    if n_members > 1:  # each member alone, to see what the ensemble adds
        for k, member in enumerate(members):
            metrics.update({f"relation.member{k}.val.{name}": float(v) for name, v in member.val_metrics.items()
                            if name in headline})
    if student is not None:  # what the student learnt of its teachers
        metrics.update({f"relation.teachers.val.{name}": float(v) for name, v in teachers_val.items() if name in headline})
        metrics["relation.student.epochs"] = float(len(student.history))
    (out_dir / CONFIG_FILE).write_text(json.dumps({
        "model": asdict(model_cfg), "inputs": asdict(in_cfg), "decode": plain_config(rel)["decode"],
        "has_roles": members[0].has_roles, "seed": seeds[0], "seeds": seeds, "ensemble": len(nets),
        "distilled_from": n_members if student is not None else None,
        "best_epoch": best_epoch, "best_epochs": [m.best_epoch for m in members], "metrics": metrics,
        "curves": history, "member_curves": [m.history for m in members[1:]],
        "student_curves": student.history if student is not None else None}, indent=1))
    # the first member's curves (an ensemble's others are in relation.json's member_curves), and the shipped student's
    plot_curves(history, out_dir / "artifacts" / "relation_curves.png")
    if student is not None:
        plot_curves(student.history, out_dir / "artifacts" / "relation_student_curves.png",
                    "student's loss (labels' + teachers' terms; val: labels')")
    shutil.rmtree(cache_dir, ignore_errors=True)  # re-croppable; would bloat the cache entry
    shutil.rmtree(out_dir / "checkpoints", ignore_errors=True)  # relation.pt holds the best weights
    shutil.rmtree(out_dir / "members", ignore_errors=True)
    return metrics


def teachers_on_every_rank(members: list) -> list:
    """The trained members' modules on every rank: rank 0 holds them (``train_member`` returns None on the others
    of a DDP launch), so under a process group their hyper-parameters and weights are broadcast from it and rebuilt,
    and all ranks then train the student together."""
    import torch.distributed as dist

    from stages.relation.lightning import RelationModule

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return [m.module for m in members]
    payload = [[(dict(m.module.hparams), m.module.state_dict()) for m in members] if members[0] is not None else None]
    dist.broadcast_object_list(payload, src=0)
    modules = []
    for hparams, state in payload[0]:
        module = RelationModule(**hparams)
        module.load_state_dict(state)
        modules.append(module.eval())
    return modules


def plain_config(node) -> dict:
    """A config node as plain, resolved Python containers (checkpoint- and JSON-safe)."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(node, resolve=True)


@dataclass
class TrainedMember:
    """One trained network of the stage: its Lightning module (best weights loaded), training curves, best
    epoch, val metrics, and what its training saw."""
    module: object
    history: list[dict]
    best_epoch: int
    val_metrics: dict[str, float]
    train_images: int
    bf16: bool
    has_roles: bool


def train_member(cfg, ds, priors, in_cfg: InputConfig, model_cfg, val: SplitInputs, seed: int, out_dir: Path,
                 index: int | str | None, start: dict | None = None, teachers: list | None = None) -> TrainedMember | None:
    """Train one relation network from ``seed`` (initial weights, shuffling, flips, augmentation and the simulated
    detections all follow it); ``index``: its place in an ensemble, or ``STUDENT`` (its checkpoints and finished
    weights then live under ``members/<index>``, so an interrupted ensemble resumes where it stopped), None for a
    lone network. ``start``: the state_dict it starts from (init=run|checkpoints), None for random weights.
    ``teachers``: trained members whose mean outputs it also learns (``relation.distill``; the student). None on a
    DDP rank other than 0."""
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import EarlyStopping

    # imported here: it loads torch, which importing this module must not
    from stages.relation.curves import CurveHistory
    from stages.relation.lightning import RelationDataModule, RelationModule, score_split
    from stages.relation.model import RelationNet

    rel, tr = cfg.relation, cfg.trainer
    plain = plain_config(rel)
    precision = resolve_precision(tr.precision, tr.accelerator)
    backbone_bf16 = precision == BF16  # the module autocasts its backbone itself; the rest trains in fp32
    channels_last = use_channels_last(bool(rel.train.channels_last), lambda: RelationNet(model_cfg).backbone,
                                      backbone_bf16, trains_on_gpu(tr.accelerator), "the relation backbone")

    def new_module(taught: bool = False):
        options = dict(model=asdict(model_cfg), loss=plain["loss"], decode=plain["decode"],
                       optim={"lr": float(rel.train.lr), "weight_decay": float(rel.train.weight_decay)},
                       backbone_bf16=backbone_bf16, select=str(rel.train.get("select", "wheel_acc")),
                       backbone_channels_last=channels_last)
        if not taught:
            return RelationModule(**options)
        from stages.relation.student import DistilledRelationModule
        return DistilledRelationModule(**options, distill=plain["distill"])

    member_dir = out_dir if index is None else out_dir / "members" / str(index)
    done = member_dir / "member.pt"
    if index is not None and done.is_file():  # finished before an interruption
        saved = torch.load(done, map_location="cpu", weights_only=True)
        module = new_module()
        module.load_state_dict(saved["state_dict"])
        return TrainedMember(module, json.loads(saved["history"]), int(saved["best_epoch"]),
                             score_split(module, val, int(rel.train.batch_size)), int(saved["train_images"]),
                             backbone_bf16, bool(saved["has_roles"]))

    L.seed_everything(seed, workers=True)
    noise = DetectionNoise.from_cfg(rel.train.get("detection_noise"))
    train_records = with_simulated_detections(_limit(ds.subset("train"), rel.train.limit_train_images), noise,
                                              seed, in_cfg.max_objects)
    # the simulated detections follow the seed, so each member crops its own training graphs
    train = split_inputs("train" if index is None else f"train_member{index}", train_records, ds.root, in_cfg,
                         priors, out_dir / "inputs", float(rel.val_min_box_px), int(rel.train.threads))
    if len(train) == 0 or len(val) == 0:
        raise ValueError(f"relation: need train and val images, got {len(train)} train and {len(val)} val")
    module = new_module(taught=teachers is not None)
    if teachers is not None:
        module.teach(teachers)
    if start is not None:  # a resumed attempt's last.ckpt (trainer.fit below) then replaces them
        module.model.load_state_dict(start)
    augment = AugmentConfig.from_cfg(plain.get("augment"))
    box_warp = BoxWarpConfig.from_cfg(plain.get("box_warp"))
    workers = loader_workers(rel.train.get("num_workers"), tr.accelerator)
    data = RelationDataModule(train, val, int(rel.train.batch_size), float(rel.train.hflip), augment, box_warp, workers)
    ckpt_dir = member_dir / "checkpoints"
    checkpoint, latest = best_and_latest(ckpt_dir, MONITOR, "max")
    history = CurveHistory()
    label = ("relation" if index is None else "relation student" if index == STUDENT
             else f"relation member {index + 1}/{int(rel.get('ensemble', 1))}")
    callbacks = [checkpoint, latest, EarlyStopping(monitor=MONITOR, mode="max", patience=int(rel.train.patience)),
                 history, *lightning_progress(label)]
    callbacks = [*weight_averaging(float(rel.train.get("ema_decay", 0.0))), *callbacks]
    logger = _tracking_logger() if index in (None, 0) else None  # one member's curves in the stage's run
    if logger is not None:  # the precision this machine trained in, beside the configured "auto"
        logger.log_hyperparams({"relation.precision": precision, "relation.channels_last": channels_last,
                                "relation.loader_workers": workers})
    trainer = L.Trainer(max_epochs=int(rel.train.epochs), accelerator=tr.accelerator, devices=tr.devices,
                        strategy=tr.strategy, num_nodes=int(tr.num_nodes), precision=FP32 if backbone_bf16 else precision,
                        logger=logger if logger is not None else False, callbacks=callbacks,
                        deterministic=True, default_root_dir=member_dir, log_every_n_steps=10,
                        enable_model_summary=False)
    last = ckpt_dir / "last.ckpt"
    trainer.fit(module, datamodule=data, ckpt_path=last if last.is_file() else None, weights_only=True)
    check_replicas_agree(module, "relation")
    if not trainer.is_global_zero:
        return None

    if not history.rows and last.is_file():  # ddp_spawn: the epochs ran in child processes
        history.load_state_dict(torch.load(last, map_location="cpu", weights_only=True)["callbacks"][history.state_key])
    best = torch.load(checkpoint.best_model_path or last, map_location="cpu", weights_only=True)
    module.load_state_dict(best["state_dict"])
    module = module.cpu()
    alone = {} if index is None else score_split(module, val, int(rel.train.batch_size))  # a lone net: run() scores it
    member = TrainedMember(module, history.rows, int(best.get("epoch", -1)), alone, len(train),
                           backbone_bf16, bool((train.role >= 0).any()))
    if index is not None:
        torch.save({"state_dict": module.state_dict(), "history": json.dumps(member.history),
                    "best_epoch": member.best_epoch, "train_images": member.train_images,
                    "has_roles": member.has_roles}, done)
        shutil.rmtree(ckpt_dir, ignore_errors=True)
    return member


def load_network(stage_dir: str | os.PathLike):
    """The trained RelationNet, or RelationEnsemble (``relation.ensemble`` > 1), in eval mode on the CPU, and
    its relation.json."""
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.relation.model import ModelConfig, RelationEnsemble, RelationNet

    stage_dir = Path(stage_dir)
    meta = json.loads((stage_dir / CONFIG_FILE).read_text())
    n_members = int(meta.get("ensemble", 1))
    model_cfg = ModelConfig.of(meta["model"])   # also a relation.json from before relation/backbone named classes
    net = RelationNet(model_cfg)
    if n_members > 1:
        net = RelationEnsemble([RelationNet(model_cfg) for _ in range(n_members)])
    net.load_state_dict(torch.load(stage_dir / WEIGHTS_FILE, map_location="cpu", weights_only=True))
    return net.eval(), meta
