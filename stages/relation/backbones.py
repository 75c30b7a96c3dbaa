"""The relation network's node encoders (docs/design.md §6): a crop tensor (M, 7, S, S) -> features (M, out_dim).

A backbone is one ``nn.Module`` class, chosen by ``_target_`` in its ``conf/relation/backbone/<name>.yaml``, which
holds exactly the keyword arguments the class takes; every backbone takes ``input_size`` (S, the crop side, also what
the graph inputs are cropped to: ``deepword.relation_graph.InputConfig``) and ``out_dim`` (``relation.model.hidden``,
given by ``build_backbone``) and keeps ``input_size`` as an attribute.

A backbone whose first operation is a convolution of the 7 input channels (then, optionally, a BatchNorm)
declares it (``FirstConv``: ``first_conv``, ``first_norm`` and ``after_first_conv``) so that the ONNX export folds
the input normalisation into it (``stages.export.onnx_export.FoldedBackbone``); one that does not exports
unfolded, with a warning and ``export.relation.folded_first_conv`` 0.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import nn

from stages.relation.backbone_spec import TARGET
from stages.training.modules import build_module

IN_CHANNELS = 7   # RGB + the four coordinate planes (deepword.relation_graph.node_tensor)


@runtime_checkable
class FirstConv(Protocol):
    """A backbone that starts with a convolution of the node tensor: ``forward(x)`` equals
    ``after_first_conv(first_norm(first_conv(x)))`` (``first_norm`` None: the convolution alone)."""

    first_conv: nn.Conv2d
    first_norm: nn.BatchNorm2d | None

    def after_first_conv(self, y: torch.Tensor) -> torch.Tensor: ...


class ConvFC(nn.Module):
    """Conv+fc node encoder: ``stages`` stride-2 conv3x3-BN-ReLU blocks (widths base*expansion*2^k), then
    a fully connected layer over the flattened map, which keeps where in the crop things are."""

    def __init__(self, input_size: int, out_dim: int, expansion: int = 1, base_channels: int = 4, stages: int = 3):
        super().__init__()
        self.input_size = int(input_size)
        layers, c_in, side = [], IN_CHANNELS, self.input_size
        for k in range(stages):
            c = base_channels * expansion * 2**k
            layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(c), nn.ReLU()]
            c_in, side = c, (side + 1) // 2
        self.features = nn.Sequential(*layers)
        self.fc = nn.Linear(c_in * side * side, out_dim)

    @property
    def first_conv(self) -> nn.Conv2d:
        return self.features[0]

    @property
    def first_norm(self) -> nn.BatchNorm2d:
        return self.features[1]

    def after_first_conv(self, y: torch.Tensor) -> torch.Tensor:
        return self.fc(torch.flatten(self.features[2:](y), 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(torch.flatten(self.features(x), 1))


class BasicBlock(nn.Module):
    """ResNet basic block: two conv3x3-BN, identity (or 1x1 projection) shortcut."""

    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = nn.Sequential()
        if stride != 1 or c_in != c_out:
            self.shortcut = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride=stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(out)) + self.shortcut(x))


class ResNet18(nn.Module):
    """ResNet-18 (He et al.): 7x7/2 stem + 3x3/2 max-pool, four stages of two basic blocks, global
    average pool, fc. ``base_width`` 64 is the standard network; smaller widths are for tests and the quick
    profile. Any ``input_size`` (the global pool makes the features size-free)."""

    def __init__(self, input_size: int, out_dim: int, base_width: int = 64):
        super().__init__()
        self.input_size = int(input_size)
        w = base_width
        self.stem = nn.Sequential(nn.Conv2d(IN_CHANNELS, w, 7, stride=2, padding=3, bias=False), nn.BatchNorm2d(w),
                                  nn.ReLU(), nn.MaxPool2d(3, stride=2, padding=1))
        blocks, c_in = [], w
        for k, stride in enumerate((1, 2, 2, 2)):
            c = w * 2**k
            blocks += [BasicBlock(c_in, c, stride), BasicBlock(c, c, 1)]
            c_in = c
        self.blocks = nn.Sequential(*blocks)
        self.fc = nn.Linear(c_in, out_dim)

    @property
    def first_conv(self) -> nn.Conv2d:
        return self.stem[0]

    @property
    def first_norm(self) -> nn.BatchNorm2d:
        return self.stem[1]

    def after_first_conv(self, y: torch.Tensor) -> torch.Tensor:
        return self.fc(self.blocks(self.stem[2:](y)).mean(dim=(2, 3)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.blocks(self.stem(x)).mean(dim=(2, 3)))


def build_backbone(spec: dict, out_dim: int) -> nn.Module:
    """The backbone a ``relation/backbone`` node (or a saved model's copy of it) describes: its ``_target_`` class
    with the node's other keys and ``out_dim`` (``stages.training.modules.build_module``)."""
    backbone = build_module(spec, "relation.backbone", out_dim=out_dim)
    if getattr(backbone, "input_size", None) != int(spec.get("input_size", -1)):
        raise TypeError(f"relation.backbone: {spec[TARGET]} must take input_size (the crop side) and keep it as "
                        "its input_size attribute")
    return backbone
