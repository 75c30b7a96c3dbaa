"""The relation network's training losses: the paper's weighted L2 on the 0/1 relation matrices, the
wheels' front/rear role, the owner ranking (an addition, ``relation.loss.rank_weight``) and the geometry
gate's own loss (an addition, ``relation.loss.gate_weight``)."""

from __future__ import annotations

import torch

from stages.relation.decode import allowed_owners, type_masks


def weighted_l2(scores: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, pos_weight: float,
                neg_weight: float) -> torch.Tensor:
    """pos_weight x mean over masked true pairs of (s - 1)^2 + neg_weight x mean over masked non-pairs of
    s^2. Averaging each class on its own keeps the many non-pairs (a wheel has one owner among all
    vehicles of a hard image) from drowning the positives, which otherwise stalls training at s = 0."""
    return balanced_squared_error(scores, target, target, mask, pos_weight, neg_weight)


def balanced_squared_error(scores: torch.Tensor, target: torch.Tensor, labels: torch.Tensor, mask: torch.Tensor,
                           pos_weight: float = 1.0, neg_weight: float = 1.0) -> torch.Tensor:
    """(s - target)^2 averaged over the masked true pairs (``labels``) and over the masked non-pairs apart, weighted:
    ``weighted_l2`` against the 0/1 labels themselves, the student's term against its teachers' scores."""
    m = mask.to(scores.dtype)
    pos = labels.to(scores.dtype) * m
    neg = m - pos
    error = (scores - target.to(scores.dtype)) ** 2
    pos_term = (pos * error).sum() / pos.sum().clamp_min(1.0)
    neg_term = (neg * error).sum() / neg.sum().clamp_min(1.0)
    return pos_weight * pos_term + neg_weight * neg_term


RANK_TEMPERATURE = 0.1  # cosines span [-1, 1]: /0.1 lets the softmax approach one-hot


def allowed_log_softmax(scores: torch.Tensor, allowed: torch.Tensor, temperature: float = RANK_TEMPERATURE) -> torch.Tensor:
    """Log-softmax of each row's scores / ``temperature`` over its allowed columns (the others get ~0 probability)."""
    return torch.log_softmax(torch.where(allowed, scores / temperature, torch.full_like(scores, -1e4)), dim=-1)


def owner_ranking(scores: torch.Tensor, target: torch.Tensor, allowed: torch.Tensor,
                  temperature: float = RANK_TEMPERATURE) -> torch.Tensor:
    """Mean cross-entropy, over wheels whose owner is among their allowed vehicles, of a softmax of the
    wheel's ownership scores / ``temperature`` over those vehicles. The one-owner decode keeps each wheel's best vehicle,
    a ranking the L2 loss trains only indirectly (it pulls every score to 0 or 1 on its own): a wheel
    inside two vehicle boxes is scored right by L2 on average while its two vehicles swap places."""
    positive = target.bool() & allowed
    has_owner = positive.any(dim=-1)
    log_p = allowed_log_softmax(scores, allowed, temperature)
    nll = -(log_p * positive.to(scores.dtype)).sum(dim=-1)
    return (nll * has_owner.to(scores.dtype)).sum() / has_owner.sum().clamp_min(1)


def relation_loss(outputs, batch: dict[str, torch.Tensor], pos_weight: float, neg_weight: float,
                  role_weight: float, rank_weight: float = 0.0, min_containment: float = 0.0,
                  gate_logits: torch.Tensor | None = None, gate_weight: float = 0.0) -> dict[str, torch.Tensor]:
    """L2 losses on candidate wheel-vehicle and wheel-wheel pairs, plus the wheels' role (front/rear) BCE,
    plus (``rank_weight`` > 0) the owner ranking over the vehicles the decode may choose (``min_containment``),
    plus (``gate_weight`` > 0) the geometry gate's own ranking: the owner ranking of its logits (B, N, N)
    over those same vehicles. Trained only through the product with the cosine, the gate stays near 1
    wherever the cosines already separate the training pairs, which they do from appearance; its own
    ranking makes it a geometric owner classifier (bottom alignment, position in the box). Measured
    (docs/domain.md): better in domain, worse on the held-out families, so it is off by default."""
    owner_scores, couple_scores, front = outputs
    wv, ww = type_masks(batch["classes"])
    cand = batch["cand"].bool()
    owner = weighted_l2(owner_scores, batch["owner"], wv & cand, pos_weight, neg_weight)
    rank = owner.new_zeros(())
    gate = owner.new_zeros(())
    if rank_weight > 0 or gate_weight > 0:
        allowed = allowed_owners(batch["classes"], cand, batch["coords"], min_containment)
    if rank_weight > 0:
        rank = owner_ranking(owner_scores, batch["owner"], allowed)
    if gate_weight > 0:
        if gate_logits is None:
            raise ValueError("relation.loss.gate_weight > 0 needs the geometry gate (relation.model.geometry_gate=true)")
        gate = owner_ranking(gate_logits, batch["owner"], allowed, temperature=1.0)
    couple = weighted_l2(couple_scores, batch["couple"], ww & cand, pos_weight, neg_weight)
    known = ((batch["role"] >= 0) & batch["valid"].bool()).to(front.dtype)
    target = batch["role"].clamp_min(0).to(front.dtype)
    p = front.clamp(1e-6, 1 - 1e-6)
    bce = -(target * torch.log(p) + (1 - target) * torch.log(1 - p))  # lets a NaN through to the loss check
    role = (bce * known).sum() / known.sum().clamp_min(1.0)
    return {"loss": owner + couple + role_weight * role + rank_weight * rank + gate_weight * gate, "owner": owner,
            "couple": couple, "role": role, "rank": rank, "gate": gate}
