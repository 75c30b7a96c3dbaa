"""Decoding detector outputs into boxes: 3x3 max-pool peak extraction and top-K, then each peak's box from
CenterNet's size and offset maps (``ctdet_decode``) or TTFNet's side distances (``ttfnet_decode``), and with the facing
head each peak's facing vector (``decode_outputs``).

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


def ctdet_boxes(wh: torch.Tensor, reg: torch.Tensor, cell: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor,
                down_ratio: int) -> torch.Tensor:
    """CenterNet's boxes (B, k, 4) in input pixels at the peaks' cells from its (B, 2, H, W) size and offset maps."""
    offset = gather_feat(reg, cell)
    size = gather_feat(wh, cell)
    cx = xs.to(wh.dtype) + offset[..., 0]
    cy = ys.to(wh.dtype) + offset[..., 1]
    half_w, half_h = size[..., 0] / 2, size[..., 1] / 2
    return torch.stack([cx - half_w, cy - half_h, cx + half_w, cy + half_h], dim=-1) * down_ratio


def ttfnet_boxes(ltrb: torch.Tensor, cell: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor,
                 down_ratio: int) -> torch.Tensor:
    """TTFNet's boxes (B, k, 4) in input pixels at the peaks' cells from its (B, 4, H, W) distances from each cell
    centre to the box sides (input pixels)."""
    d = gather_feat(ltrb, cell)
    cx = (xs.to(ltrb.dtype) + 0.5) * down_ratio
    cy = (ys.to(ltrb.dtype) + 0.5) * down_ratio
    return torch.stack([cx - d[..., 0], cy - d[..., 1], cx + d[..., 2], cy + d[..., 3]], dim=-1)


def ctdet_decode(heat: torch.Tensor, wh: torch.Tensor, reg: torch.Tensor, k: int = 100,
                 down_ratio: int = 4) -> torch.Tensor:
    """(B, C, H, W) heatmap probabilities, (B, 2, H, W) sizes and offsets -> (B, k, 6) detections
    ``x1, y1, x2, y2, score, class`` in network-input pixels, best first."""
    return decode_outputs((heat, wh, reg), k, down_ratio, "centernet")


def ttfnet_decode(heat: torch.Tensor, ltrb: torch.Tensor, k: int = 100, down_ratio: int = 4) -> torch.Tensor:
    """(B, C, H, W) heatmap probabilities and (B, 4, H, W) distances from each cell centre to the box sides
    (input pixels) -> (B, k, 6) detections ``x1, y1, x2, y2, score, class`` in network-input pixels."""
    return decode_outputs((heat, ltrb), k, down_ratio, "ttfnet")


def decode_outputs(outputs: tuple[torch.Tensor, ...], k: int = 100, down_ratio: int = 4, regression: str | None = None,
                   facing: bool = False) -> torch.Tensor:
    """The heads' ``outputs`` -> (B, k, 6) detections ``x1, y1, x2, y2, score, class`` in network-input pixels, best
    first; with ``facing`` (the heads' last map is the facing head's) (B, k, 8): then the facing vector (dx, dy) at
    each peak. ``regression`` names the box heads (``centernet``: size and offset maps, ``ttfnet``: side
    distances); None: told by their number (three maps are CenterNet's, two TTFNet's)."""
    heat, maps = outputs[0], tuple(outputs[1:-1] if facing else outputs[1:])
    if regression is None:
        regression = "centernet" if len(maps) == 2 else "ttfnet"
    k = min(k, heat.shape[1] * heat.shape[2] * heat.shape[3])
    scores, cell, classes, ys, xs = topk(nms_heatmap(heat), k)
    if regression == "centernet":
        boxes = ctdet_boxes(*maps, cell, ys, xs, down_ratio)
    else:
        boxes = ttfnet_boxes(*maps, cell, ys, xs, down_ratio)
    detections = with_scores(boxes, scores, classes)
    if facing:
        detections = torch.cat([detections, gather_feat(outputs[-1], cell)], dim=-1)
    return detections
