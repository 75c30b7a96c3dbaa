"""A relation backbone that lives outside the project's packages (tests/stages/export/test_toy_backbone.py): one
module and one config node (toy_conf/relation/backbone/toy.yaml) are all a new backbone takes."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ToyBackbone(nn.Module):
    """One 3x3 / 2 convolution with a bias and no BatchNorm, ReLU, global average pool, fc. It declares its first
    convolution (stages.relation.backbones.FirstConv), so the export folds the input normalisation into it."""

    first_norm = None   # the convolution's own bias is its shift

    def __init__(self, input_size: int, out_dim: int, width: int = 8):
        super().__init__()
        self.input_size = input_size
        self.conv = nn.Conv2d(7, width, 3, stride=2, padding=1)
        self.fc = nn.Linear(width, out_dim)

    @property
    def first_conv(self) -> nn.Conv2d:
        return self.conv

    def after_first_conv(self, y: torch.Tensor) -> torch.Tensor:
        return self.fc(F.relu(y).mean(dim=(2, 3)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.after_first_conv(self.conv(x))


class UndeclaredToyBackbone(nn.Module):
    """The same network without declaring its first convolution: exported unfolded, and said so."""

    def __init__(self, input_size: int, out_dim: int, width: int = 8):
        super().__init__()
        self.input_size = input_size
        self.body = nn.Sequential(nn.Conv2d(7, width, 3, stride=2, padding=1), nn.ReLU())
        self.fc = nn.Linear(width, out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.body(x).mean(dim=(2, 3)))
