"""CenterNet's losses: the penalty-reduced focal loss on the heatmap and L1 losses on size and offset."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def focal_loss(pred: torch.Tensor, gt: torch.Tensor, alpha: float = 2.0, beta: float = 4.0) -> torch.Tensor:
    """CenterNet's ``_neg_loss``: a variant of focal loss on heatmaps with Gaussian-softened negatives,

        pos (gt == 1):  -(1 - p)^alpha * log(p)
        neg (gt < 1):   -(1 - gt)^beta * p^alpha * log(1 - p)

    summed over the whole batch and divided by the number of objects (peaks); with no object in the
    batch, the negative term alone. ``pred`` are probabilities already clamped away from 0 and 1.
    """
    pos = gt.eq(1).float()
    neg = 1.0 - pos
    pos_loss = (torch.log(pred) * torch.pow(1 - pred, alpha) * pos).sum()
    neg_loss = (torch.log(1 - pred) * torch.pow(pred, alpha) * torch.pow(1 - gt, beta) * neg).sum()
    num_pos = pos.sum()
    if num_pos == 0:
        return -neg_loss
    return -(pos_loss + neg_loss) / num_pos


def gather_feat(feature: torch.Tensor, ind: torch.Tensor) -> torch.Tensor:
    """Pick per-object values from a (B, C, H, W) map at flat indices ``ind`` (B, K) -> (B, K, C)."""
    b, c = feature.shape[:2]
    flat = feature.reshape(b, c, -1).permute(0, 2, 1)
    return flat.gather(1, ind.unsqueeze(2).expand(-1, -1, c))


def reg_l1_loss(output: torch.Tensor, mask: torch.Tensor, ind: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's ``RegL1Loss``: L1 between the map ``output`` read at the objects' cells and ``target``
    (B, K, 2), over real objects only, divided by the number of regressed values."""
    pred = gather_feat(output, ind)
    m = mask.unsqueeze(2).expand_as(pred).float()
    loss = F.l1_loss(pred * m, target * m, reduction="sum")
    return loss / (m.sum() + 1e-4)


def centernet_loss(outputs: tuple[torch.Tensor, torch.Tensor, torch.Tensor], batch: dict[str, torch.Tensor],
                   hm_weight: float = 1.0, wh_weight: float = 0.1, off_weight: float = 1.0
                   ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss ``hm_weight * focal + wh_weight * L1(size) + off_weight * L1(offset)`` and its parts."""
    heat, wh, reg = outputs
    parts = {
        "hm": focal_loss(heat, batch["hm"]),
        "wh": reg_l1_loss(wh, batch["mask"], batch["ind"], batch["wh"]),
        "off": reg_l1_loss(reg, batch["mask"], batch["ind"], batch["reg"]),
    }
    total = hm_weight * parts["hm"] + wh_weight * parts["wh"] + off_weight * parts["off"]
    return total, parts
