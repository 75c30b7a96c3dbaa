"""The detector's output heads, each Conv3x3 -> ReLU -> Conv1x1: the class heatmap, then the box regression of
``detector.regression``: CenterNet's box size and centre offset at the centre cell, or TTFNet's distances
from each cell's centre to the four sides of its box; with ``detector.facing``, last, the facing map: at a vehicle's
centre cell the image direction from its rear to its front (deepword/facing.py)."""

from __future__ import annotations

import torch
from torch import nn

# Initial heatmap logit: sigmoid(-2.19) = 0.1, the prior probability of a peak, so that the focal loss of
# the many background cells does not swamp the first steps (CenterNet, after RetinaNet's prior init).
HEATMAP_BIAS = -2.19
# Clamp of the heatmap sigmoid, as CenterNet's ``_sigmoid``: keeps log(p) and log(1 - p) finite.
HEATMAP_EPS = 1e-4
# TTFNet's ``wh_offset_base``: the distance head's output is ReLU(x) times this many input pixels, so its raw
# outputs stay near 1 for boxes from a few pixels to a few hundred.
LTRB_BASE = 16.0
# Initial distance bias: ReLU(1) x 16 = 16 px to each side, a 32 px box; with a zero bias half the cells would
# start in ReLU's flat half and never learn.
LTRB_BIAS = 1.0
REGRESSIONS = ("centernet", "ttfnet")


def head(c_in: int, head_conv: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, head_conv, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(head_conv, c_out, 1))


class CenterNetHeads(nn.Module):
    """Heatmap (one channel per class, clamped sigmoid) and the regression maps: ``centernet``: size (w, h)
    in output cells and offset (dx, dy); ``ttfnet``: one map of distances (left, top, right, bottom) in input
    pixels; ``facing``: then a map of (dx, dy), read at vehicle centres."""

    def __init__(self, c_in: int, head_conv: int, num_classes: int, regression: str = "centernet",
                 facing: bool = False):
        super().__init__()
        if regression not in REGRESSIONS:
            raise ValueError(f"detector.regression: unknown {regression!r} (have {', '.join(REGRESSIONS)})")
        self.regression = regression
        self.hm = head(c_in, head_conv, num_classes)
        nn.init.constant_(self.hm[-1].bias, HEATMAP_BIAS)
        if regression == "centernet":
            self.wh = head(c_in, head_conv, 2)
            self.reg = head(c_in, head_conv, 2)
            branches = (self.wh, self.reg)
        else:
            self.ltrb = head(c_in, head_conv, 4)
            branches = (self.ltrb,)
        self.facing = head(c_in, head_conv, 2) if facing else None
        bias = LTRB_BIAS if regression == "ttfnet" else 0.0
        for branch in branches:
            nn.init.normal_(branch[-1].weight, std=0.001)
            nn.init.constant_(branch[-1].bias, bias)
        if self.facing is not None:  # starts near (0, 0): no opinion, which the footprints read as no vote
            nn.init.normal_(self.facing[-1].weight, std=0.001)
            nn.init.constant_(self.facing[-1].bias, 0.0)

    @property
    def has_facing(self) -> bool:
        return self.facing is not None

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        # In fp32 even under bf16 autocast: bf16 rounds 1 - 1e-4 to 1 (log(1 - p) = -inf in the focal loss),
        # and its 8-bit mantissa would put decoded box corners ~2 input pixels off.
        heat = torch.clamp(torch.sigmoid(self.hm(x).float()), HEATMAP_EPS, 1 - HEATMAP_EPS)
        if self.regression == "centernet":
            boxes = (self.wh(x).float(), self.reg(x).float())
        else:
            boxes = (torch.relu(self.ltrb(x).float()) * LTRB_BASE,)
        if self.facing is None:
            return heat, *boxes
        return heat, *boxes, self.facing(x).float()
