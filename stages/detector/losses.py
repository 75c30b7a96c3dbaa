"""The detector's losses: CenterNet's penalty-reduced focal loss on the heatmap with either CenterNet's L1
losses on size and offset at each centre cell, or TTFNet's Gaussian-weighted GIoU loss on the boxes that every
cell near a centre predicts (``detector.regression``)."""

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


def cell_centres(height: int, width: int, down_ratio: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W) x and y of each output cell's centre in input pixels: where a cell's box distances start."""
    ys = (torch.arange(height, device=device, dtype=torch.float32) + 0.5) * down_ratio
    xs = (torch.arange(width, device=device, dtype=torch.float32) + 0.5) * down_ratio
    return xs.expand(height, width), ys[:, None].expand(height, width)


def ltrb_to_boxes(ltrb: torch.Tensor, down_ratio: int) -> torch.Tensor:
    """(B, 4, H, W) distances from each cell centre to the box's left, top, right and bottom sides (input
    pixels) -> (B, 4, H, W) boxes x1, y1, x2, y2 in input pixels."""
    cx, cy = cell_centres(ltrb.shape[2], ltrb.shape[3], down_ratio, ltrb.device)
    return torch.stack([cx - ltrb[:, 0], cy - ltrb[:, 1], cx + ltrb[:, 2], cy + ltrb[:, 3]], dim=1)


def generalized_iou(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """GIoU (Rezatofighi et al., CVPR 2019) of paired boxes (..., 4) x1 y1 x2 y2: IoU minus the share of
    the smallest enclosing box that neither covers. In [-1, 1]; unlike IoU it still has a gradient when the
    boxes do not overlap, and unlike L1 on sizes it weighs a 10 px error on an 8 px wheel more than on a
    200 px vehicle."""
    area_a = (a[..., 2] - a[..., 0]).clamp(min=0) * (a[..., 3] - a[..., 1]).clamp(min=0)
    area_b = (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)
    iw = (torch.minimum(a[..., 2], b[..., 2]) - torch.maximum(a[..., 0], b[..., 0])).clamp(min=0)
    ih = (torch.minimum(a[..., 3], b[..., 3]) - torch.maximum(a[..., 1], b[..., 1])).clamp(min=0)
    inter = iw * ih
    union = area_a + area_b - inter
    enclosing = ((torch.maximum(a[..., 2], b[..., 2]) - torch.minimum(a[..., 0], b[..., 0]))
                 * (torch.maximum(a[..., 3], b[..., 3]) - torch.minimum(a[..., 1], b[..., 1])))
    return inter / (union + eps) - (enclosing - union) / (enclosing + eps)


def giou_box_loss(ltrb: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, down_ratio: int) -> torch.Tensor:
    """TTFNet's regression loss: sum over sample cells of weight x (1 - GIoU(predicted box, target box)),
    divided by the summed weight of the batch. ``ltrb`` (B, 4, H, W) predicted distances, ``target`` (B, 4,
    H, W) boxes and ``weight`` (B, H, W) from ``targets.ttfnet_box_targets``."""
    cells = weight > 0
    if not bool(cells.any()):
        return ltrb.sum() * 0.0
    pred = ltrb_to_boxes(ltrb, down_ratio).permute(0, 2, 3, 1)[cells]
    truth = target.permute(0, 2, 3, 1)[cells]
    w = weight[cells]
    return (w * (1.0 - generalized_iou(pred, truth))).sum() / (w.sum() + 1e-4)


def ttfnet_loss(outputs: tuple[torch.Tensor, torch.Tensor], batch: dict[str, torch.Tensor], down_ratio: int,
                hm_weight: float = 1.0, giou_weight: float = 5.0) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss ``hm_weight * focal + giou_weight * GIoU`` (TTFNet's weights: 1 and 5) and its parts."""
    heat, ltrb = outputs
    parts = {"hm": focal_loss(heat, batch["hm"]),
             "giou": giou_box_loss(ltrb, batch["box"], batch["box_weight"], down_ratio)}
    return hm_weight * parts["hm"] + giou_weight * parts["giou"], parts


def facing_loss(facing: torch.Tensor, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """L1 between the facing map read at the objects' centre cells and their unit facing vectors, over the objects
    that have one (``targets.facing_targets``); 0 (with a gradient path) where the batch has none."""
    if "facing" not in batch or not bool(batch["facing_mask"].any()):
        return facing.sum() * 0.0
    return reg_l1_loss(facing, batch["facing_mask"], batch["ind"], batch["facing"])


def facing_agreement(facing: torch.Tensor, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """(1, 2): how many of the batch's objects with a facing target the map points within 90 deg of it, and how many
    have one (the val split's ``val/facing_acc``)."""
    pred = gather_feat(facing.float(), batch["ind"])
    known = batch["facing_mask"] > 0
    right = ((pred * batch["facing"]).sum(-1) > 0) & known
    return torch.stack([right.sum(), known.sum()]).to(torch.float32)[None]


def detector_loss(outputs: tuple[torch.Tensor, ...], batch: dict[str, torch.Tensor], regression: str,
                  down_ratio: int, weights: dict[str, float]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of ``detector.regression`` (``centernet`` or ``ttfnet``) with its weights from
    ``detector.loss`` (each kind reads its own: hm/wh/off or hm/giou); outputs with one map more than the regression
    has are the facing head's (last): ``facing_weight`` x ``facing_loss`` is added."""
    n_boxes = {"centernet": 3, "ttfnet": 2}.get(regression)
    if n_boxes is None:
        raise ValueError(f"detector.regression: unknown {regression!r} (have 'centernet', 'ttfnet')")
    boxes = tuple(outputs[:n_boxes])
    if regression == "centernet":
        total, parts = centernet_loss(boxes, batch, weights.get("hm_weight", 1.0), weights.get("wh_weight", 0.1),
                                      weights.get("off_weight", 1.0))
    else:
        total, parts = ttfnet_loss(boxes, batch, down_ratio, weights.get("hm_weight", 1.0),
                                   weights.get("giou_weight", 5.0))
    if len(outputs) > n_boxes:
        parts["facing"] = facing_loss(outputs[n_boxes], batch)
        total = total + weights.get("facing_weight", 0.5) * parts["facing"]
    return total, parts
