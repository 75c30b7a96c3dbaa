"""PyTorch -> ONNX for the relation network and the detector, checked with ``onnx.checker``.

Exporter: ``torch.onnx.export(..., dynamo=False)``, the TorchScript tracer, chosen knowingly (PITFALLS):
both networks are free of data-dependent control flow (masking is arithmetic, top-K has a fixed K), so
tracing captures them exactly; it needs no ``onnxscript`` dependency and writes one self-contained file
that older embedded runtimes read (opset 17). The exported graphs are checked by the parity tests.

What is exported:
- relation: ``RelationGraph`` = the node tensor of DESIGN §6 (uint8 crops -> [0, 1] RGB + four coordinate
  planes, ``stages.relation.inputs.node_tensor``) + ``RelationNet``: the trained module, the PyTorch
  reference of parity and latency. What is exported is ``ShippedRelation``, the same function rewritten
  for inference speed (``FoldedBackbone``: the /255 and the first BatchNorm folded into the first
  convolution; dynamic variant: the backbone runs on real objects only).
  Inputs crops (B, N, 3, S, S) uint8, coords (B, N, 4), adj (B, N, N), cand (B, N, N) float; outputs
  owner, couple (B, N, N), front (B, N). Decisions (0.5 threshold, one owner) stay outside the graph
  (``stages.export.decode``): onnxruntime has no boolean EyeLike kernel, and an embedded runtime applies
  its own post-processing anyway. ``static``: N fixed to max_objects (batch dynamic), static shapes
  throughout; ``dynamic``: batch and N dynamic.
- detector: ``DetectorGraph`` = CenterNet + ``ctdet_decode`` (peak extraction and top-K), dynamic batch;
  outputs the three heads and the (B, K, 6) detections, so a runtime needs no post-processing.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from stages.export.runtime import DETECTOR_INPUT, DETECTOR_OUTPUTS, RELATION_INPUTS, RELATION_OUTPUTS
from stages.relation.inputs import node_tensor

OPSET = 17


class RelationGraph(nn.Module):
    """What the relation ONNX model computes: node tensors from uint8 crops, then the network."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, crops, coords, adj, cand):
        return self.net(node_tensor(crops, coords), adj, cand)


class FoldedBackbone(nn.Module):
    """``backbone(node_tensor(crops, coords))`` with the /255 of the RGB channels and the first BatchNorm
    (eval mode: a per-channel affine map) folded into the first convolution's weights and bias, so the
    graph goes uint8 -> Cast -> Concat(planes) -> Conv with no division and no separate normalisation (the
    same function up to float rounding). Measured alternatives (onnxruntime 1.31, one thread, 133 objects):
    the unfolded graph 15.6 ms; this 14.3 ms; the coordinate planes' response computed as a matmul and
    added after a 3-channel convolution 16-18 ms (onnxruntime cannot fuse that add into its blocked
    convolution and reorders the tensor twice). Backbones: ``ConvFC`` and ``ResNet18``."""

    def __init__(self, backbone: nn.Module):
        super().__init__()
        from stages.relation.model import ConvFC, ResNet18

        if isinstance(backbone, ConvFC):
            conv, bn, self.body, self.pool = backbone.features[0], backbone.features[1], backbone.features[2:], False
        elif isinstance(backbone, ResNet18):
            conv, bn, self.pool = backbone.stem[0], backbone.stem[1], True
            self.body = nn.Sequential(*backbone.stem[2:], backbone.blocks)
        else:
            raise TypeError(f"FoldedBackbone: no folding for {type(backbone).__name__}")
        self.fc = backbone.fc
        self.stride, self.padding = conv.stride, conv.padding
        with torch.no_grad():
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            weight = conv.weight * scale[:, None, None, None]
            weight[:, :3] /= 255.0  # the RGB channels arrive as 0..255
            self.register_buffer("weight", weight)
            self.register_buffer("bias", bn.bias - bn.running_mean * scale)

    @staticmethod
    def supports(backbone: nn.Module) -> bool:
        from stages.relation.model import ConvFC, ResNet18

        return isinstance(backbone, ConvFC | ResNet18)

    def forward(self, crops: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """crops (M, 3, S, S) uint8, coords (M, 4) -> (M, hidden)."""
        planes = coords.to(torch.float32)[..., None, None].expand(*coords.shape, *crops.shape[-2:])
        x = torch.cat([crops.to(torch.float32), planes], dim=1)
        y = self.body(F.conv2d(x, self.weight, self.bias, self.stride, self.padding))
        return self.fc(y.mean(dim=(2, 3)) if self.pool else torch.flatten(y, 1))


class ShippedRelation(nn.Module):
    """What the relation ONNX models compute: ``RelationGraph`` with ``FoldedBackbone`` (when the backbone
    has a folding). ``real_only`` (the dynamic variant): the backbone, most of the cost, runs only on
    real objects, gathered by their non-zero coordinates (``pad_graphs`` pads with all-zero boxes), and
    padded nodes get zero features. Padding is masked out of every output that counts (no edges, not a
    candidate: ``stages.export.parity``), so a batch of images padded to its largest costs the backbone
    only its real objects. The static variant keeps static shapes throughout (no NonZero) for embedded
    runtimes, so it runs the backbone on every slot."""

    def __init__(self, net: nn.Module, real_only: bool):
        super().__init__()
        self.net, self.real_only = net, real_only
        folded = FoldedBackbone.supports(net.backbone)
        self.backbone = FoldedBackbone(net.backbone) if folded else None

    def embed(self, crops: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        if self.backbone is None:
            return self.net.backbone(node_tensor(crops, coords))
        return self.backbone(crops, coords)

    def forward(self, crops, coords, adj, cand):
        b, n = crops.shape[0], crops.shape[1]
        flat_crops, flat_coords = crops.flatten(0, 1), coords.flatten(0, 1).to(torch.float32)
        if self.real_only:
            real = torch.nonzero(flat_coords.abs().sum(-1) > 0).squeeze(1)
            h = torch.zeros(b * n, self.net.cfg.hidden, dtype=torch.float32)
            h = h.index_put((real,), self.embed(flat_crops[real], flat_coords[real]))
        else:
            h = self.embed(flat_crops, flat_coords)
        return self.net.relate(h.view(b, n, -1), adj, cand, coords.to(torch.float32))


class DetectorGraph(nn.Module):
    """What the detector ONNX model computes: heads and decoded top-K detections in input pixels."""

    def __init__(self, net: nn.Module, k: int):
        super().__init__()
        self.net, self.k = net, k

    def forward(self, images):
        from stages.detector.decode import ctdet_decode
        from stages.detector.model import DOWN_RATIO

        heat, wh, reg = self.net(images)
        return heat, wh, reg, ctdet_decode(heat, wh, reg, k=self.k, down_ratio=DOWN_RATIO)


def _export(module: nn.Module, args: tuple, path: Path, input_names, output_names, dynamic_axes) -> Path:
    import onnx

    module.eval()
    with warnings.catch_warnings():  # the tracer warns about every shape it reads; the parity check decides
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, str(path), dynamo=False, opset_version=OPSET, do_constant_folding=True,
                          input_names=list(input_names), output_names=list(output_names),
                          dynamic_axes=dynamic_axes)
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    return path


def relation_example(n: int, input_size: int, batch: int = 2) -> tuple[torch.Tensor, ...]:
    """Tracing inputs: a fully connected graph of valid nodes, so no branch of the network is idle."""
    gen = torch.Generator().manual_seed(0)
    crops = torch.randint(0, 256, (batch, n, 3, input_size, input_size), dtype=torch.uint8, generator=gen)
    coords = torch.rand((batch, n, 4), generator=gen)
    adj = torch.rand((batch, n, n), generator=gen)
    return crops, coords, adj, torch.ones((batch, n, n))


def export_relation(net: nn.Module, path: Path, input_size: int, max_objects: int, static: bool) -> Path:
    """Export the relation network; ``static``: N = max_objects fixed, else N dynamic (batch always dynamic)."""
    nodes = {} if static else {1: "objects"}
    pairs = {} if static else {1: "objects", 2: "objects"}
    axes = {name: {0: "batch", **nodes} for name in ("crops", "coords", "front")}
    axes.update({name: {0: "batch", **pairs} for name in ("adj", "cand", "owner", "couple")})
    # the dynamic variant is traced with fewer nodes than max_objects, so no size is baked in by accident
    n = max_objects if static else max(2, max_objects // 2 + 1)
    example = relation_example(n, input_size)
    shipped = ShippedRelation(net.eval(), real_only=not static)
    return _export(shipped, example, path, RELATION_INPUTS, RELATION_OUTPUTS, axes)


def export_detector(net: nn.Module, path: Path, input_width: int, input_height: int, k: int) -> Path:
    example = (torch.zeros((2, 3, input_height, input_width)),)
    axes = {DETECTOR_INPUT: {0: "batch"}, **{name: {0: "batch"} for name in DETECTOR_OUTPUTS}}
    return _export(DetectorGraph(net, k), example, path, (DETECTOR_INPUT,), DETECTOR_OUTPUTS, axes)

