"""The student of ``relation.distill``: one relation network trained against the labels and its teachers, the trained
ensemble's members (docs/domain.md, "One network taught by the three").

The ensemble (``model.RelationEnsemble``) decides on the mean of its members' scores: steadier held out than any one
network, at three times the inference. A student network of the same architecture trains on the same graphs (its
own seed: shuffling, flips, augmentation, simulated detections) against the labels, as a member does, and against the
members' mean outputs on the very crops it sees (after augmentation), so it learns the ensemble's function, not only
the labels. It then ships alone: one network's inference.

The teachers are plain attributes of the student's module, not sub-modules: the checkpoint, the weight average and
the optimiser hold the student alone, and Lightning's ``train()`` never switches the teachers out of eval mode.
"""

from __future__ import annotations

import torch

from deepword.word_format import WHEEL
from stages.relation.decode import allowed_owners, type_masks
from stages.relation.distill import DistillConfig
from stages.relation.lightning import RelationModule
from stages.relation.losses import RANK_TEMPERATURE, allowed_log_softmax, balanced_squared_error
from stages.relation.model import mean_outputs


def ranking_kl(scores: torch.Tensor, teacher: torch.Tensor, allowed: torch.Tensor,
               temperature: float = RANK_TEMPERATURE) -> torch.Tensor:
    """KL divergence of the student's softmax over each wheel's allowed vehicles (the owner ranking's, at its
    temperature) from the teachers': the order the one-owner decode reads, taught as the teachers hold it. Mean over
    wheels with at least two allowed vehicles (one has nothing to rank); 0 where the two rank alike."""
    log_p = allowed_log_softmax(scores, allowed, temperature)
    log_t = allowed_log_softmax(teacher, allowed, temperature)
    kl = (log_t.exp() * (log_t - log_p) * allowed.to(scores.dtype)).sum(dim=-1)
    ranked = (allowed.sum(dim=-1) >= 2).to(scores.dtype)
    return (kl * ranked).sum() / ranked.sum().clamp_min(1.0)


def binary_kl(p: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Element-wise KL divergence of Bernoulli(p) from Bernoulli(t): the front probabilities' term."""
    p, t = p.clamp(1e-6, 1 - 1e-6), t.clamp(1e-6, 1 - 1e-6)
    return t * (torch.log(t) - torch.log(p)) + (1 - t) * (torch.log(1 - t) - torch.log(1 - p))


def distillation_loss(outputs, teacher, batch: dict[str, torch.Tensor], role_weight: float, rank_weight: float,
                      min_containment: float) -> torch.Tensor:
    """The student's outputs (owner, couple, front) against the teachers' mean: balanced L2 on the candidate
    wheel-vehicle and wheel-wheel scores, the owner ranking's KL divergence (weighted like the labels' ranking
    term), and the front probabilities' KL divergence on the real wheels (weighted like the labels' role term). 0 where
    the student answers as its teachers do."""
    owner, couple, front = outputs
    t_owner, t_couple, t_front = teacher
    wv, ww = type_masks(batch["classes"])
    cand = batch["cand"].bool()
    # the true pairs and the non-pairs (by the labels) averaged apart, as the labels' own L2
    loss = (balanced_squared_error(owner, t_owner, batch["owner"], wv & cand)
            + balanced_squared_error(couple, t_couple, batch["couple"], ww & cand))
    if rank_weight > 0:
        allowed = allowed_owners(batch["classes"], cand, batch["coords"], min_containment)
        loss = loss + rank_weight * ranking_kl(owner, t_owner, allowed)
    wheels = ((batch["classes"] == WHEEL) & batch["valid"].bool()).to(front.dtype)
    return loss + role_weight * (binary_kl(front, t_front) * wheels).sum() / wheels.sum().clamp_min(1.0)


class DistilledRelationModule(RelationModule):
    """A RelationModule whose training loss adds the teachers' term (``distillation_loss``) to the labels'.
    Validation, selection and the saved weights are a plain RelationModule's; ``teach`` hands it the trained
    members before ``fit``."""

    def __init__(self, *args, distill: dict | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.distill = DistillConfig(**(distill or {}))

    def teach(self, teachers: list[RelationModule]) -> None:
        for t in teachers:
            t.eval().requires_grad_(False)
        object.__setattr__(self, "_teachers", list(teachers))  # not sub-modules: see the module docstring

    def on_fit_start(self) -> None:
        for t in getattr(self, "_teachers", ()):  # on the student's device (a GPU run moves the student only)
            t.to(self.device)

    def training_step(self, batch, batch_idx):
        teachers = getattr(self, "_teachers", None)
        if not teachers:
            raise RuntimeError("DistilledRelationModule: no teachers (call teach() with the trained members first)")
        outputs = self(batch)
        with torch.no_grad():
            teacher = mean_outputs([t(batch) for t in teachers])
        lc = self.hparams.loss
        labels = self._loss(outputs, batch)["loss"]
        taught = distillation_loss(outputs, teacher, batch, float(lc["role_weight"]), float(lc.get("rank_weight", 0.0)),
                                   float(self.hparams.decode.get("min_containment", 0.0)))
        loss = self.distill.label_weight * labels + self.distill.weight * taught
        if not torch.isfinite(loss):
            raise FloatingPointError(f"relation student: training loss is {loss.item()} (labels {labels.item()}, "
                                     f"teachers {taught.item()}) at epoch {self.current_epoch}, batch {batch_idx}")
        self.log("train/loss", loss, on_step=False, on_epoch=True, prog_bar=True, batch_size=len(batch["classes"]))
        self.log("train/taught", taught, on_step=False, on_epoch=True, batch_size=len(batch["classes"]))
        return loss
