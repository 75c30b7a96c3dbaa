"""Decoding detector outputs into boxes: 3x3 max-pool peak extraction and top-K, then each peak's box from
CenterNet's size and offset maps (``ctdet_decode``) or TTFNet's side distances (``ttfnet_decode``).

Pure tensor operations with no data-dependent shapes or Python loops over the batch, so the decoder
exports to ONNX together with the network (dynamic batch, fixed K).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from stages.detector.losses import gather_feat


def nms_heatmap(heat: torch.Tensor, kernel: int = 3) -> torch.Tensor:
    """CenterNet's ``_nms``: keep a heatmap value only where it is the maximum of its k x k neighbourhood."""
    hmax = F.max_pool2d(heat, kernel, stride=1, padding=(kernel - 1) // 2)
    return heat * (hmax == heat).to(heat.dtype)


def topk(heat: torch.Tensor, k: int) -> tuple[torch.Tensor, ...]:
    """The ``k`` highest peaks over all classes: (scores, flat cell indices, classes, ys, xs), each (B, k)."""
    b, c, h, w = heat.shape
    scores, flat = torch.topk(heat.reshape(b, -1), k)
    classes = torch.div(flat, h * w, rounding_mode="floor")
    cell = flat - classes * (h * w)
    ys = torch.div(cell, w, rounding_mode="floor")
    xs = cell - ys * w
    return scores, cell, classes, ys, xs


def with_scores(boxes: torch.Tensor, scores: torch.Tensor, classes: torch.Tensor) -> torch.Tensor:
    """(B, k, 4) boxes, (B, k) scores and classes -> (B, k, 6) detections ``x1, y1, x2, y2, score, class``."""
    return torch.cat([boxes, scores.unsqueeze(-1), classes.to(boxes.dtype).unsqueeze(-1)], dim=-1)


def ctdet_decode(heat: torch.Tensor, wh: torch.Tensor, reg: torch.Tensor, k: int = 100,
                 down_ratio: int = 4) -> torch.Tensor:
    """(B, C, H, W) heatmap probabilities, (B, 2, H, W) sizes and offsets -> (B, k, 6) detections
    ``x1, y1, x2, y2, score, class`` in network-input pixels, best first."""
    k = min(k, heat.shape[1] * heat.shape[2] * heat.shape[3])
    scores, cell, classes, ys, xs = topk(nms_heatmap(heat), k)
    offset = gather_feat(reg, cell)
    size = gather_feat(wh, cell)
    cx = xs.to(heat.dtype) + offset[..., 0]
    cy = ys.to(heat.dtype) + offset[..., 1]
    half_w, half_h = size[..., 0] / 2, size[..., 1] / 2
    boxes = torch.stack([cx - half_w, cy - half_h, cx + half_w, cy + half_h], dim=-1) * down_ratio
    return with_scores(boxes, scores, classes)


def ttfnet_decode(heat: torch.Tensor, ltrb: torch.Tensor, k: int = 100, down_ratio: int = 4) -> torch.Tensor:
    """(B, C, H, W) heatmap probabilities and (B, 4, H, W) distances from each cell centre to the box sides
    (input pixels) -> (B, k, 6) detections ``x1, y1, x2, y2, score, class`` in network-input pixels."""
    k = min(k, heat.shape[1] * heat.shape[2] * heat.shape[3])
    scores, cell, classes, ys, xs = topk(nms_heatmap(heat), k)
    d = gather_feat(ltrb, cell)
    cx = (xs.to(heat.dtype) + 0.5) * down_ratio
    cy = (ys.to(heat.dtype) + 0.5) * down_ratio
    boxes = torch.stack([cx - d[..., 0], cy - d[..., 1], cx + d[..., 2], cy + d[..., 3]], dim=-1)
    return with_scores(boxes, scores, classes)


def decode_outputs(outputs: tuple[torch.Tensor, ...], k: int = 100, down_ratio: int = 4) -> torch.Tensor:
    """The decoder of whichever heads produced ``outputs``: three maps (heatmap, size, offset) are
    CenterNet's, two (heatmap, side distances) TTFNet's."""
    if len(outputs) == 3:
        return ctdet_decode(*outputs, k=k, down_ratio=down_ratio)
    return ttfnet_decode(*outputs, k=k, down_ratio=down_ratio)
