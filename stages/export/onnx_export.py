"""PyTorch -> ONNX for the relation network and the detector, checked with ``onnx.checker``.

Exporter: ``torch.onnx.export(..., dynamo=False)``, the TorchScript tracer, chosen knowingly (PITFALLS):
both networks are free of data-dependent control flow (masking is arithmetic, top-K has a fixed K), so
tracing captures them exactly; it needs no ``onnxscript`` dependency and writes one self-contained file
that older embedded runtimes read (opset 17). The exported graphs are checked by the parity tests.

What is exported:
- relation: ``RelationGraph`` = the node tensor of DESIGN §6 (uint8 crops -> [0, 1] RGB + four coordinate
  planes, ``stages.relation.inputs.node_tensor``) + ``RelationNet``. Inputs crops (B, N, 3, S, S) uint8,
  coords (B, N, 4), adj (B, N, N), cand (B, N, N) float; outputs owner, couple (B, N, N), front (B, N).
  Decisions (0.5 threshold, one owner) stay outside the graph (``stages.export.decode``): onnxruntime
  has no boolean EyeLike kernel, and an embedded runtime applies its own post-processing anyway.
  ``static``: N fixed to max_objects (batch dynamic); ``dynamic``: batch and N dynamic.
- detector: ``DetectorGraph`` = CenterNet + ``ctdet_decode`` (peak extraction and top-K), dynamic batch;
  outputs the three heads and the (B, K, 6) detections, so a runtime needs no post-processing.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
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
    return _export(RelationGraph(net), example, path, RELATION_INPUTS, RELATION_OUTPUTS, axes)


def export_detector(net: nn.Module, path: Path, input_width: int, input_height: int, k: int) -> Path:
    example = (torch.zeros((2, 3, input_height, input_width)),)
    axes = {DETECTOR_INPUT: {0: "batch"}, **{name: {0: "batch"} for name in DETECTOR_OUTPUTS}}
    return _export(DetectorGraph(net, k), example, path, (DETECTOR_INPUT,), DETECTOR_OUTPUTS, axes)

