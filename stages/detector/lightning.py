"""Lightning wrappers: the CenterNet training module and the data module over a WORD dataset's splits."""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from deepword.detection.average_precision import coco_average_precision
from deepword.detection.letterbox import MEAN, STD, letterbox_for
from deepword.word_format import Record
from stages.detector.dataset import CenterNetDataset, max_objects_of
from stages.detector.losses import detector_loss, facing_agreement
from stages.detector.model import CLASS_NAMES, DOWN_RATIO, build_centernet
from stages.detector.predict import detections_to_record
from stages.training.loader_workers import usable_cores


class NonFiniteLossError(FloatingPointError):
    pass


def check_finite_loss(total: torch.Tensor, parts: dict[str, torch.Tensor], epoch: int, step: int) -> None:
    """Stop training with a clear message as soon as the loss is NaN or infinite."""
    if not torch.isfinite(total):
        detail = ", ".join(f"{k}={float(v):.4g}" for k, v in parts.items())
        raise NonFiniteLossError(f"detector: non-finite training loss {float(total)} at epoch {epoch}, step {step} "
                                 f"({detail}); lower detector.optimizer.lr or check the input boxes")


def batch_to_input(images: torch.Tensor, memory_format=torch.contiguous_format) -> torch.Tensor:
    """(B, H, W, 3) uint8 RGB batch -> (B, 3, H, W) float network input, ImageNet-normalised as
    ``letterbox.normalise`` does per image. The permuted NHWC batch already has channels_last strides."""
    mean = torch.as_tensor(MEAN, device=images.device).view(1, 3, 1, 1)
    std = torch.as_tensor(STD, device=images.device).view(1, 3, 1, 1)
    x = images.permute(0, 3, 1, 2).to(torch.float32) / 255.0
    return ((x - mean) / std).contiguous(memory_format=memory_format)


class CenterNetModule(L.LightningModule):
    """Trains a CenterNet; at the end of each validation epoch computes COCO AP per class on the val set
    (``val/ap50.<class>``, ``val/ap.<class>`` in percent, and their class mean ``val/ap50`` to monitor), with
    ground-truth boxes under ``ap_min_box_px`` ignored as in the stage's reported AP."""

    def __init__(self, model_cfg: dict, loss: dict, optimizer: dict, score_threshold: float,
                 ap_min_box_px: float = 0.0, channels_last: bool = False):
        super().__init__()
        self.save_hyperparameters()
        self.net = build_centernet(model_cfg)
        # channels_last (NHWC) lets oneDNN run its convolutions and BatchNorm without reordering every
        # activation; with bf16 autocast it is the larger half of the measured speed-up.
        self.memory_format = torch.channels_last if channels_last else torch.contiguous_format
        self.net = self.net.to(memory_format=self.memory_format)
        self.k = int(model_cfg["max_detections"])
        self.input_size = (int(model_cfg["input_width"]), int(model_cfg["input_height"]))
        self.loss_weights, self.optim_cfg, self.score_threshold = loss, optimizer, score_threshold
        self.regression = self.net.heads.regression
        self.ap_min_box_px = ap_min_box_px
        self._val_detections: list[torch.Tensor] = []
        self._val_indices: list[torch.Tensor] = []
        self._val_facing: list[torch.Tensor] = []
        self.frozen: tuple[str, ...] = ()

    def freeze(self, parts) -> None:
        """Keep the network's named parts (``backbone``, ``heads``) at their starting weights: no gradients, and their
        batch normalisation in eval mode during training (``on_train_epoch_start``), so their running statistics
        stay the starting ones too: a few dozen new images would otherwise redraw them."""
        for part in parts:
            getattr(self.net, part).requires_grad_(False)
        self.frozen = tuple(parts)

    def on_train_epoch_start(self) -> None:
        for part in self.frozen:  # Lightning set every module to train mode before this hook
            getattr(self.net, part).eval()

    def forward(self, images: torch.Tensor):
        return self.net(images.contiguous(memory_format=self.memory_format))

    def loss(self, outputs, batch):
        return detector_loss(outputs, batch, self.regression, DOWN_RATIO, self.loss_weights)

    def training_step(self, batch, batch_idx):
        total, parts = self.loss(self(batch_to_input(batch["image"], self.memory_format)), batch)
        check_finite_loss(total, parts, self.current_epoch, self.global_step)
        bs = batch["image"].shape[0]
        self.log("train/loss", total, prog_bar=True, on_step=True, on_epoch=True, batch_size=bs)
        self.log_dict({f"train/{k}": v for k, v in parts.items()}, batch_size=bs)
        return total

    def validation_step(self, batch, batch_idx):
        outputs = self(batch_to_input(batch["image"], self.memory_format))
        total, _ = self.loss(outputs, batch)
        self.log("val/loss", total, prog_bar=True, batch_size=batch["image"].shape[0], sync_dist=True)
        self._val_detections.append(self.net.decode(outputs, self.k)[..., :6])
        if self.net.heads.has_facing and "facing" in batch:
            self._val_facing.append(facing_agreement(outputs[-1], batch))
        self._val_indices.append(batch["index"])

    def on_validation_epoch_end(self):
        if not self._val_detections:
            return
        detections, indices = torch.cat(self._val_detections), torch.cat(self._val_indices)
        self._val_detections, self._val_indices = [], []
        # Under DDP each rank saw a share of the val set (padded with repeats): gather all, keep each once.
        detections = self.all_gather(detections).reshape(-1, *detections.shape[1:])
        indices = self.all_gather(indices).reshape(-1)
        records: list[Record] = self.trainer.val_dataloaders.dataset.records
        first = {int(i): n for n, i in reversed(list(enumerate(indices.tolist())))}
        order = sorted(first)
        dets = detections.cpu().numpy()
        preds = [detections_to_record(dets[first[i]], records[i],
                                      letterbox_for(records[i].width, records[i].height, *self.input_size),
                                      self.score_threshold) for i in order]
        ap = coco_average_precision(preds, [records[i] for i in order], CLASS_NAMES, self.ap_min_box_px)
        values = {f"val/{m}.{c}": v[m] for c, v in ap.items() for m in ("ap50", "ap")}
        values = {k: (0.0 if math.isnan(v) else v) for k, v in values.items()}
        self.log_dict(values)
        self.log("val/ap50", float(np.mean([values[f"val/ap50.{c}"] for c in CLASS_NAMES])), prog_bar=True)
        if self._val_facing:
            # the share of val vehicles (ground-truth centres) whose facing the head points the right way, within 90 deg
            agree = self.all_gather(torch.cat(self._val_facing).sum(0)).reshape(-1, 2).sum(0)
            self._val_facing = []
            if float(agree[1]) > 0:
                self.log("val/facing_acc", 100.0 * float(agree[0] / agree[1]))

    def configure_optimizers(self):
        # fused: the whole update in one kernel (torch >= 2.4 on CPU, CUDA), not a dozen ops per tensor: ~2 ms
        # against 7-11 ms a step for the detector's 82 parameter tensors on 2 cores, the same algorithm rounded
        # differently (``make bench`` prints both)
        opt = torch.optim.AdamW(self.parameters(), lr=self.optim_cfg["lr"], weight_decay=self.optim_cfg["weight_decay"],
                                fused=True)
        total = max(1, int(self.trainer.estimated_stepping_batches))
        warmup = max(1, int(total * self.optim_cfg["warmup_fraction"]))

        def warmup_cosine(step: int) -> float:
            # Linear warm-up (Adam on randomly initialised BatchNorm nets is fragile in its first steps),
            # then cosine decay to zero at the last step.
            if step < warmup:
                return (step + 1) / warmup
            return 0.5 * (1 + math.cos(math.pi * min(1.0, (step - warmup) / max(1, total - warmup))))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, warmup_cosine)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


class CloseMosaic(L.Callback):
    """YOLOv8's ``close_mosaic``: the last ``epochs`` training epochs see single images only, as the detector will
    at test time -- whole vehicles at their own scale, the boxes its last steps fit (``CenterNetDataset.mosaic``).
    Set at each epoch's start, so a run resumed from a checkpoint closes it again."""

    def __init__(self, epochs: int):
        self.epochs = int(epochs)

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        open_ = trainer.current_epoch < trainer.max_epochs - self.epochs
        trainer.datamodule.train_set.mosaic_open.fill_(open_)


class DetectorDataModule(L.LightningDataModule):
    """Train (augmented, shuffled) and val (plain) loaders over WORD records of one dataset root, with the
    targets of the model's box ``regression`` (``model_config(...)["regression"]``)."""

    def __init__(self, root: str | Path, train: list[Record], val: list[Record], input_width: int,
                 input_height: int, augment: dict, batch_size: int, num_workers: int, min_overlap: float,
                 regression: str):
        super().__init__()
        if not train:
            raise ValueError("detector: the dataset's train split is empty")
        if not val:
            raise ValueError("detector: the dataset's val split is empty (needed to pick the best checkpoint)")
        max_objects = max_objects_of(train + val)
        size = dict(input_width=input_width, input_height=input_height, max_objects=max_objects,
                    min_overlap=min_overlap, regression=regression)
        self.train_set = CenterNetDataset(root, train, augment=augment, **size)
        self.val_set = CenterNetDataset(root, val, augment=None, **size)
        self.batch_size, self.num_workers = batch_size, num_workers

    def setup(self, stage: str) -> None:
        """Every image decoded and letterboxed once, before any loader worker is forked (``CenterNetDataset.preload``)."""

        threads = usable_cores()
        self.train_set.preload(threads)
        self.val_set.preload(threads)

    def _loader(self, dataset: CenterNetDataset, train: bool) -> DataLoader:
        return DataLoader(dataset, batch_size=self.batch_size, shuffle=train, num_workers=self.num_workers,
                          drop_last=train and len(dataset) > self.batch_size,  # no 1-image BatchNorm batch
                          persistent_workers=self.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, train=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, train=False)
