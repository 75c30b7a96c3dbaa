"""Lightning wrappers of the relation network: dataset and data module over cached split inputs, and the
training module (decoding, metrics). The network itself is ``model.RelationNet``, its losses ``losses``."""

from __future__ import annotations

from dataclasses import fields

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset
from torchmetrics import MeanMetric, Metric

from deepword.metrics import Counts
from deepword.relation_graph import SplitInputs, mirror_coords, node_tensor
from stages.relation.augment import AugmentConfig, augment_crops
from stages.relation.decode import (
    ROLE_KEYS,
    decode_couples,
    decode_owners,
    metrics_from_counts,
    relation_counts,
    role_counts,
    role_percentages,
)
from stages.relation.losses import relation_loss
from stages.relation.model import ModelConfig, RelationNet, pair_geometry
from stages.relation.warp import BoxWarpConfig, random_box_warp

COUNT_KEYS = tuple(f.name for f in fields(Counts))  # the §7 counts, summed across batches (and ranks)
# What selects the checkpoint and stops training (``relation.train.select``): val wheel_acc, or the val loss.
# One val wheel is ~0.3 points of wheel_acc on the quick data and the in-domain val saturates within a few
# epochs, so on wheel_acc the first epoch to reach the plateau wins and training stops `patience` epochs
# later; the val loss keeps falling for all 30 quick epochs. Measured on the held-out validation draw
# (docs/domain.md): the loss-selected late epochs score higher in domain but not held out.
SELECT_MODES = ("wheel_acc", "loss")


PAD_VALUES = {"classes": -1, "role": -1}  # padded nodes: no class, no role; every other field 0
PAIR_FIELDS = ("adj", "cand", "owner", "couple")  # (N, N) per image


class GraphDataset(Dataset):
    """One graph per image, unpadded (``collate_graphs`` pads a batch to its largest graph, not to
    max_objects: padding never changes real outputs, and most images hold far fewer objects, so the
    backbone, the N x N graph part and the copies all shrink). ``hflip``: probability of mirroring an
    image's graph left-right (crops flipped, x coordinates mirrored); distance ratios, adjacency,
    targets and roles are unchanged by it. ``augment``: appearance augmentation of the crops
    (``augment.augment_crops``), for training only. ``box_warp``: a random lens-like warp of the image's
    boxes (``warp.random_box_warp``), for training only."""

    def __init__(self, split: SplitInputs, hflip: float = 0.0, augment: AugmentConfig | None = None,
                 box_warp: BoxWarpConfig | None = None):
        self.split = split
        self.crops = torch.from_numpy(split.crops)
        self.offsets = split.offsets
        self.tensors = {k: torch.from_numpy(getattr(split, k)) for k in
                        ("coords", "classes", "valid", "adj", "cand", "owner", "couple", "role", "evaluated")}
        self.hflip = hflip
        self.augment = augment if augment is not None and augment.active else None
        self.box_warp = box_warp if box_warp is not None and box_warp.active else None

    def __len__(self) -> int:
        return len(self.split)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        start, stop = int(self.offsets[i]), int(self.offsets[i + 1])
        k = stop - start
        item = {key: v[i, :k, :k] if v.dim() == 3 and key != "coords" else v[i, :k] for key, v in self.tensors.items()}
        item["classes"] = item["classes"].long()
        item["role"] = item["role"].long()
        crops = self.crops[start:stop]
        if self.hflip > 0 and torch.rand(()) < self.hflip:
            crops = crops.flip(-1)
            item["coords"] = mirror_coords(item["coords"])
        if self.box_warp is not None:
            item["coords"] = random_box_warp(item["coords"], self.box_warp)
        if self.augment is not None:
            crops = augment_crops(crops, self.augment)
        item["crops"] = crops
        return item


def collate_graphs(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack graphs padded to the batch's largest node count (at least 1): node fields along dim 0,
    pair fields (N x N) along dims 0 and 1."""
    n = max([len(item["classes"]) for item in items] + [1])
    batch = {}
    for key, first in items[0].items():
        shape = (len(items), n, n) if key in PAIR_FIELDS else (len(items), n, *first.shape[1:])
        out = torch.full(shape, PAD_VALUES.get(key, 0), dtype=first.dtype)
        for b, item in enumerate(items):
            k = len(item["classes"])
            if key in PAIR_FIELDS:
                out[b, :k, :k] = item[key]
            else:
                out[b, :k] = item[key]
        batch[key] = out
    return batch


class RelationDataModule(L.LightningDataModule):
    """``num_workers`` loader processes for the training graphs (``stages.training.loader_workers``: none on a CPU, several
    on a GPU, where the crops' augmentation in the training process, ~4-6 ms an image on one core, would bound
    the epoch); validation has no augmentation and stays in the training process."""

    def __init__(self, train: SplitInputs, val: SplitInputs, batch_size: int, hflip: float = 0.0,
                 augment: AugmentConfig | None = None, box_warp: BoxWarpConfig | None = None, num_workers: int = 0):
        super().__init__()
        self.train_split, self.val_split = train, val
        self.batch_size, self.hflip, self.augment, self.box_warp = batch_size, hflip, augment, box_warp
        self.num_workers = int(num_workers)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(GraphDataset(self.train_split, self.hflip, self.augment, self.box_warp),
                          batch_size=self.batch_size, shuffle=True, collate_fn=collate_graphs,
                          num_workers=self.num_workers, persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(GraphDataset(self.val_split), batch_size=self.batch_size, collate_fn=collate_graphs)


class RelationCounts(Metric):
    """Sums of ``decode.relation_counts`` and ``decode.role_counts`` over batches (and processes, under DDP)."""

    def __init__(self, **metric_options):
        super().__init__(**metric_options)
        for key in COUNT_KEYS + ROLE_KEYS:
            self.add_state(key, default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, counts: dict[str, torch.Tensor]) -> None:
        for key in COUNT_KEYS + ROLE_KEYS:
            setattr(self, key, getattr(self, key) + counts[key].to(torch.long))

    def compute(self) -> dict[str, float]:
        """The §7 percentages and the role head's ``role_acc`` / ``order_acc`` (where roles are known)."""
        return {**metrics_from_counts({k: float(getattr(self, k)) for k in COUNT_KEYS}),
                **role_percentages({k: float(getattr(self, k)) for k in ROLE_KEYS})}

    def update_batch(self, decisions: tuple[torch.Tensor, torch.Tensor], front: torch.Tensor,
                     batch: dict[str, torch.Tensor]) -> None:
        """Adds one batch: its (owner, couple) decisions and the role head's front probabilities."""
        pred_owner, pred_couple = decisions
        self.update({**relation_counts(pred_owner, batch["owner"], pred_couple, batch["couple"], batch["classes"],
                                       batch["evaluated"]),
                     **role_counts(front, batch["role"], batch["valid"], batch["couple"])})


class RelationModule(L.LightningModule):
    """Training and validation of RelationNet. Hyper-parameters are plain dicts (checkpoint-safe)."""

    def __init__(self, model: dict, loss: dict, decode: dict, optim: dict, backbone_bf16: bool = False,
                 select: str = "wheel_acc", backbone_channels_last: bool = False):
        super().__init__()
        if select not in SELECT_MODES:
            raise ValueError(f"relation.train.select must be one of {SELECT_MODES}, got {select!r}")
        self.save_hyperparameters()
        self.model = RelationNet(ModelConfig.of(model))
        self.val_counts = RelationCounts()
        self.val_loss = MeanMetric()  # the epoch's mean val loss, for select=loss
        # bf16 autocast and channels_last for the crop backbone only, which holds nearly all the FLOPs; the
        # graph part and the cosines stay fp32, where bf16's 8-bit mantissa would blur the 0.5 decisions.
        self.backbone_bf16 = backbone_bf16
        self.backbone_format = torch.channels_last if backbone_channels_last else torch.contiguous_format
        self.model.backbone.to(memory_format=self.backbone_format)

    def node_features(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Backbone features of the valid nodes only (padding and masked objects are skipped, which also
        keeps them out of BatchNorm statistics); zeros elsewhere. Same values as ``model.embed``."""
        valid = batch["valid"].bool()
        x = node_tensor(batch["crops"][valid], batch["coords"][valid], self.backbone_format == torch.channels_last)
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=self.backbone_bf16):
            feats = self.model.backbone(x).float()
        h = feats.new_zeros((*valid.shape, feats.shape[-1]))
        h[valid] = feats
        return h

    def forward(self, batch: dict[str, torch.Tensor]):
        return self.model.relate(self.node_features(batch), batch["adj"], batch["cand"], batch["coords"])

    def _loss(self, outputs, batch):
        lc = self.hparams.loss
        gate_weight = lc.get("gate_weight", 0.0)
        gate_logits = None
        if gate_weight > 0 and self.model.gate is not None:
            gate_logits = self.model.gate.logits(pair_geometry(batch["coords"]))
        return relation_loss(outputs, batch, lc["pos_weight"], lc["neg_weight"], lc["role_weight"],
                             lc.get("rank_weight", 0.0), self.hparams.decode.get("min_containment", 0.0),
                             gate_logits, gate_weight)

    def training_step(self, batch, batch_idx):
        losses = self._loss(self(batch), batch)
        loss = losses["loss"]
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"relation: training loss is {loss.item()} (owner {losses['owner'].item()}, couple "
                f"{losses['couple'].item()}, role {losses['role'].item()}) at epoch {self.current_epoch}, batch "
                f"{batch_idx}; training stopped. Check the inputs for NaN/inf or lower relation.train.lr.")
        self.log("train/loss", loss, on_step=False, on_epoch=True, prog_bar=True, batch_size=len(batch["classes"]))
        return loss

    def decide(self, outputs, batch):
        dc = self.hparams.decode
        owner_scores, couple_scores, _ = outputs
        pred_owner = decode_owners(owner_scores, batch["classes"], batch["cand"], dc["threshold"], dc["one_owner"],
                                   batch["coords"], dc.get("min_containment", 0.0))
        pred_couple = decode_couples(couple_scores, batch["classes"], batch["cand"], dc["threshold"])
        return pred_owner, pred_couple

    def validation_step(self, batch, batch_idx):
        outputs = self(batch)
        loss = self._loss(outputs, batch)["loss"]
        self.log("val/loss", loss, on_epoch=True, batch_size=len(batch["classes"]), sync_dist=True)
        self.val_loss.update(loss.detach(), len(batch["classes"]))
        self.val_counts.update_batch(self.decide(outputs, batch), outputs[2], batch)

    def on_validation_epoch_end(self):
        metrics = self.val_counts.compute()
        self.val_counts.reset()
        mean_loss = float(self.val_loss.compute())
        self.val_loss.reset()
        wheel_acc = metrics.pop("wheel_acc")
        self.log("val/wheel_acc", wheel_acc, prog_bar=True)
        # the checkpoint and early-stopping callbacks maximise val/select
        loss_selects = self.hparams.get("select", "wheel_acc") == "loss"
        self.log("val/select", -mean_loss if loss_selects else wheel_acc)
        self.log_dict({f"val/{k}": v for k, v in metrics.items()})

    def configure_optimizers(self):
        oc = self.hparams.optim
        opt = torch.optim.AdamW(self.parameters(), lr=oc["lr"], weight_decay=oc["weight_decay"])
        epochs = max(int(self.trainer.max_epochs or 1), 1)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs, eta_min=oc["lr"] * 0.01)
        return {"optimizer": opt, "lr_scheduler": sched}


@torch.no_grad()
def score_split(module: RelationModule | list[RelationModule], split: SplitInputs, batch_size: int) -> dict[str, float]:
    """The relation metrics (percent) of a trained module on a split, in eval mode, on the CPU; of a list of
    modules (an ensemble's members), deciding on the mean of their scores."""
    # imported here: it loads torch, which importing this module must not
    from stages.relation.model import mean_outputs

    modules = [m.eval() for m in (module if isinstance(module, list) else [module])]
    # Scored by one process (rank 0 after a DDP fit, the others have left): nothing to gather from other ranks.
    counts = RelationCounts(sync_on_compute=False)
    for batch in DataLoader(GraphDataset(split), batch_size=batch_size, collate_fn=collate_graphs):
        outputs = mean_outputs([m(batch) for m in modules])
        counts.update_batch(modules[0].decide(outputs, batch), outputs[2], batch)
    return counts.compute()
