"""Backbones producing a stride-4 feature map for the CenterNet heads (the ``detector/backbone`` group).

A backbone is one ``nn.Module`` class named by ``_target_`` in its ``conf/detector/backbone/<name>.yaml``, which holds
exactly the keyword arguments it takes (``build_backbone``); it keeps ``out_channels`` (the heads' input width) and
``stride_multiple`` (what input sides must be divisible by). The same file sets the heads' ``detector.head_conv``.

- ``resnet18``: CenterNet's plain ``res_18`` (msra_resnet): ResNet-18 basic blocks down to stride 32,
  then three 4x4 stride-2 transposed convolutions of 256/256/256 channels back up to stride 4.
  Written here (no torchvision), randomly initialised.
- ``tiny``: the CPU default. Stride-2 stages of one basic block each (stride 2..32), then a small
  top-down path (nearest upsampling + 1x1 lateral skips, as in FPN) back to stride 4. The skips carry the
  fine detail small wheels need that a deconvolution stack would have to relearn.

All operations export to ONNX with a dynamic batch dimension.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from stages.training.modules import TARGET, build_module

# a backbone's name in a model.json written before ``_target_`` named its class (``build_backbone`` reads those too)
LEGACY_BACKBONES = {"tiny": "stages.detector.backbones.TinyBackbone",
                    "resnet18": "stages.detector.backbones.ResNet18Deconv"}


def conv_bn_relu(c_in: int, c_out: int, stride: int = 1, kernel: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, kernel, stride, kernel // 2, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class BasicBlock(nn.Module):
    """ResNet's basic block: two 3x3 convolutions with a (projected when shapes change) identity shortcut."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = None
        if stride != 1 or c_in != c_out:
            self.downsample = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


def resnet_layer(c_in: int, c_out: int, blocks: int, stride: int) -> nn.Sequential:
    layers = [BasicBlock(c_in, c_out, stride)] + [BasicBlock(c_out, c_out) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class ResNet18Deconv(nn.Module):
    """ResNet-18 (stride 32) + three transposed-conv upsamplings (stride 4): CenterNet's ``res_18``."""

    stride_multiple = 32  # input sizes must be divisible by this

    def __init__(self, deconv_channels: tuple[int, ...] = (256, 256, 256)):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True),
                                  nn.MaxPool2d(3, 2, 1))
        self.layer1 = resnet_layer(64, 64, 2, 1)
        self.layer2 = resnet_layer(64, 128, 2, 2)
        self.layer3 = resnet_layer(128, 256, 2, 2)
        self.layer4 = resnet_layer(256, 512, 2, 2)
        deconvs, c_in = [], 512
        for c_out in deconv_channels:
            deconvs += [nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
            c_in = c_out
        self.deconv = nn.Sequential(*deconvs)
        self.out_channels = c_in
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.layer4(self.layer3(self.layer2(self.layer1(self.stem(x)))))
        return self.deconv(x)


class TinyBackbone(nn.Module):
    """Stem (stride 2) + ``blocks`` basic blocks (default one) per further stride-2 stage (``channels[1:]``,
    strides 4, 8, ...), then
    a top-down path (nearest upsampling, 1x1 lateral, 3x3 smoothing) back to stride 4. Five channel widths
    reach stride 32, whose receptive field covers the nearest vehicles (half the image wide)."""

    def __init__(self, channels: tuple[int, ...] = (16, 32, 64, 128, 256), out_channels: int = 32,
                 blocks: tuple[int, ...] | None = None):
        super().__init__()
        if len(channels) < 3:
            raise ValueError(f"detector.backbone.channels: need at least 3 widths (stem, stride 4, stride 8), got {channels}")
        blocks = tuple(blocks) if blocks is not None else (1,) * (len(channels) - 1)
        if len(blocks) != len(channels) - 1 or min(blocks) < 1:
            raise ValueError(f"detector.backbone.blocks: need one count >= 1 per stage after the stem "
                             f"({len(channels) - 1} for channels {list(channels)}), got {list(blocks)}")
        self.stem = conv_bn_relu(3, channels[0], stride=2)
        # a single block stays a bare BasicBlock: the weight names of models saved before ``blocks`` existed
        self.stages = nn.ModuleList(BasicBlock(a, b, stride=2) if n == 1 else resnet_layer(a, b, n, stride=2)
                                    for a, b, n in zip(channels[:-1], channels[1:], blocks, strict=True))
        self.laterals = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in channels[1:])
        self.smooths = nn.ModuleList(conv_bn_relu(out_channels, out_channels) for _ in channels[2:])
        self.out_channels = out_channels
        self.stride_multiple = 2 ** len(channels)  # input sizes must be divisible by the deepest stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        features, x = [], self.stem(x)
        for stage in self.stages:
            x = stage(x)
            features.append(x)
        p = self.laterals[-1](features[-1])
        for f, lateral, smooth in zip(features[-2::-1], self.laterals[-2::-1], self.smooths[::-1], strict=True):
            p = smooth(lateral(f) + F.interpolate(p, scale_factor=2.0, mode="nearest"))
        return p


def backbone_spec(cfg: dict) -> dict:
    """The backbone node (``_target_`` and the class's arguments) of ``detector.backbone`` or a model.json's copy of
    it; one written before ``_target_`` (``name: tiny|resnet18``, with the heads' ``head_conv`` beside the backbone's
    arguments) is translated."""
    cfg = dict(cfg)
    if TARGET in cfg or "name" not in cfg:
        return cfg
    name = cfg.pop("name")
    if name not in LEGACY_BACKBONES:
        raise ValueError(f"detector.backbone.name: unknown backbone {name!r} (have {', '.join(LEGACY_BACKBONES)})")
    cfg.pop("head_conv", None)
    return {TARGET: LEGACY_BACKBONES[name], **cfg}


def build_backbone(cfg: dict) -> nn.Module:
    """A backbone from its config node (``detector.backbone``, ``backbone_spec``)."""
    return build_module(backbone_spec(cfg), "detector.backbone")
