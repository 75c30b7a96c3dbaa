"""The facing network: which way a vehicle's front lies in its crop (deepword/facing.py, docs/bev.md "Front and
back"). A small convolutional classifier of the vehicle box's crop, apart from the relation network: the front/back
cue (light strips a few pixels tall, where the cabin sits along the body) needs more of the crop than the relation
backbone's three stride-2 layers keep, and it is read only for the vehicles the footprints place, not for every node
of every relation graph."""

from __future__ import annotations

import torch
from torch import nn


def _block(c_in: int, c_out: int, convs: int = 2) -> nn.Sequential:
    """``convs`` conv3x3-BN-ReLU layers and a 2x2 max-pool."""
    layers = []
    for i in range(convs):
        layers += [nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out),
                   nn.ReLU()]
    return nn.Sequential(*layers, nn.MaxPool2d(2))


class FacingNet(nn.Module):
    """uint8 crops (B, 3, S, S) -> (B, 2): the direction from the vehicle's rear to its front in crop pixels, its
    length the network's certainty (``deepword.inference.facing_net`` turns it into image pixels)."""

    def __init__(self, widths: tuple[int, ...] = (24, 48, 64, 96), hidden: int = 64,
                 convs: tuple[int, ...] | None = None):
        super().__init__()
        convs = tuple(convs) if convs is not None else (2,) * len(widths)
        if len(convs) != len(widths) or min(convs) < 1:
            raise ValueError(f"facing.convs: need one count >= 1 per width ({len(widths)} for widths {list(widths)}), "
                             f"got {list(convs)}")
        layers, c_in = [], 3
        for c, n in zip(widths, convs, strict=True):
            layers.append(_block(c_in, c, n))
            c_in = c
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(c_in, hidden), nn.ReLU(), nn.Linear(hidden, 2))

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        x = crops.to(torch.float32) / 255.0
        return self.head(self.features(x).mean(dim=(2, 3)))


FACING_SHARPNESS = 4.0  # the loss's logistic slope on the projection of the vector onto the true direction


def facing_loss(vectors: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Mean softplus(-FACING_SHARPNESS x <vector, target>) over unit ``targets``: a logistic loss on which way the
    vector points along the true direction, so that its length grows with the network's certainty."""
    return nn.functional.softplus(-FACING_SHARPNESS * (vectors * targets).sum(-1)).mean()
