"""CenterNet's output heads: Conv3x3 -> ReLU -> Conv1x1 for the class heatmap, box size and offset."""

from __future__ import annotations

import torch
from torch import nn

# Initial heatmap logit: sigmoid(-2.19) = 0.1, the prior probability of a peak, so that the focal loss of
# the many background cells does not swamp the first steps (CenterNet, after RetinaNet's prior init).
HEATMAP_BIAS = -2.19
# Clamp of the heatmap sigmoid, as CenterNet's ``_sigmoid``: keeps log(p) and log(1 - p) finite.
HEATMAP_EPS = 1e-4


def head(c_in: int, head_conv: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, head_conv, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(head_conv, c_out, 1))


class CenterNetHeads(nn.Module):
    """Heatmap (one channel per class, clamped sigmoid), size (w, h) and offset (dx, dy) maps."""

    def __init__(self, c_in: int, head_conv: int, num_classes: int):
        super().__init__()
        self.hm = head(c_in, head_conv, num_classes)
        self.wh = head(c_in, head_conv, 2)
        self.reg = head(c_in, head_conv, 2)
        nn.init.constant_(self.hm[-1].bias, HEATMAP_BIAS)
        for branch in (self.wh, self.reg):
            nn.init.normal_(branch[-1].weight, std=0.001)
            nn.init.zeros_(branch[-1].bias)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # In fp32 even under bf16 autocast: bf16 rounds 1 - 1e-4 to 1 (log(1 - p) = -inf in the focal loss),
        # and its 8-bit mantissa would put decoded box corners ~2 input pixels off.
        heat = torch.clamp(torch.sigmoid(self.hm(x).float()), HEATMAP_EPS, 1 - HEATMAP_EPS)
        return heat, self.wh(x).float(), self.reg(x).float()
