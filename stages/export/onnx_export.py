"""PyTorch -> ONNX for the relation network and the detector, checked with ``onnx.checker``.

Exporter: ``torch.onnx.export(..., dynamo=False)``, the TorchScript tracer, chosen knowingly (PITFALLS):
both networks are free of data-dependent control flow (masking is arithmetic, top-K has a fixed K), so
tracing captures them exactly; it needs no ``onnxscript`` dependency and writes one self-contained file
that older embedded runtimes read (opset 17). The exported graphs are checked by the parity tests.

What is exported:
- relation: ``RelationGraph`` = the node tensor of docs/design.md §6 (uint8 crops -> [0, 1] RGB + four coordinate
  planes, ``deepword.relation_graph.node_tensor``) + ``RelationNet``: the trained module, the PyTorch
  reference of parity and latency. What is exported is ``ShippedRelation``, the same function rewritten
  for inference speed (``FoldedBackbone``: the /255 and the first BatchNorm folded into the first
  convolution, the coordinate planes' share of it a small convolution on a grid; dynamic variant: the
  backbone runs on real objects only), with its tensors' shapes named (``name_object_dims``).
  Inputs crops (B, N, 3, S, S) uint8, coords (B, N, 4), adj (B, N, N), cand (B, N, N) float; outputs
  owner, couple (B, N, N), front (B, N). Decisions (0.5 threshold, one owner) stay outside the graph
  (``deepword.inference.decode``): onnxruntime has no boolean EyeLike kernel, and an embedded runtime applies
  its own post-processing anyway. ``static``: N fixed to max_objects (batch dynamic), static shapes
  throughout; ``dynamic``: batch and N dynamic. An ensemble (``relation.ensemble``) is exported as one graph
  that runs every member and averages their outputs (``ShippedEnsemble``).
- facing: ``stages.facing.model.FacingNet`` as it is: uint8 crops (B, 3, S, S) -> facing (B, 2), batch dynamic.
- detector: ``DetectorGraph`` = CenterNet + its decoding (peak extraction and top-K), dynamic batch;
  outputs the heads' maps and the (B, K, 6) detections ((B, K, 8) with the facing head: its vector at each peak),
  so a runtime needs no post-processing.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from deepword.inference.runtime import DETECTOR_INPUT, RELATION_INPUTS, RELATION_OUTPUTS, detector_outputs
from deepword.relation_graph import node_tensor
from stages.export.channels_first import ChannelsFirstGraph
from stages.relation.backbones import IN_CHANNELS, FirstConv
from stages.relation.model import RelationEnsemble, mean_outputs

OPSET = 17
log = logging.getLogger(__name__)


class RelationGraph(nn.Module):
    """What the relation ONNX model computes: node tensors from uint8 crops, then the network."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, crops, coords, adj, cand):
        return self.net(node_tensor(crops, coords), adj, cand)


def plane_responses(weight: torch.Tensor, size: int, stride, padding) -> torch.Tensor:
    """What a convolution's input channels give on a constant plane of ones (S x S, zero-padded):
    weight (C_out, C_in, k, k) -> (C_in, C_out, OH, OW), in float64 (an exactness check follows)."""
    ones = torch.ones(1, 1, size, size, dtype=torch.float64)
    return torch.stack([F.conv2d(ones, weight[:, c : c + 1].double(), None, stride, padding)[0]
                        for c in range(weight.shape[1])])


def grid_mask(out_shape, dtype=torch.float32) -> torch.Tensor:
    """(1, 1, OH+1, OW+1): 0 on the first row and column, 1 elsewhere (see ``corner_kernel``)."""
    mask = torch.ones(1, 1, out_shape[0] + 1, out_shape[1] + 1, dtype=dtype)
    mask[..., 0, :] = 0
    mask[..., :, 0] = 0
    return mask


def plane_grid(coords: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """coords (M, 4) -> (M, 4, OH+1, OW+1): each coordinate everywhere but on the first row and column
    (``mask`` = ``grid_mask``)."""
    return coords[..., None, None] * mask


def corner_kernel(responses: torch.Tensor) -> torch.Tensor | None:
    """A 2x2 kernel K (C_out, C_in, 2, 2) with ``conv2d(plane_grid(coords), K)`` equal to the first
    convolution's response to the constant coordinate planes, or None where no such kernel exists.

    A constant plane's response differs from its interior value only where the kernel hangs over the
    zero padding. With a 3x3 / stride 2 / padding 1 convolution of an even-sized input that is the first
    output row and column alone, so the response takes four values: r00 at the corner, r01 along the
    first row, r10 along the first column, r11 inside. A 2x2 convolution of a grid that is 0 on its first
    row and column and 1 elsewhere gives K11 at the corner, K10 + K11 along the first row, K01 + K11
    along the first column and the sum of all four inside, which solves for K. Other geometries (a 7x7 /
    2 stem with padding 3, an odd input size) have more distinct border values: the result is checked
    against every response pixel, per plane, and None is returned when any differs."""
    r00, r01, r10, r11 = (responses[..., i, j] for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
    top = torch.stack([r11 - r01 - r10 + r00, r10 - r00], dim=-1)
    bottom = torch.stack([r01 - r00, r00], dim=-1)
    kernel = torch.stack([top, bottom], dim=-2).transpose(0, 1)  # (C_out, C_in, 2, 2)
    mask = grid_mask(responses.shape[-2:], torch.float64)
    ones = torch.ones(1, responses.shape[0], dtype=torch.float64)
    for c in range(responses.shape[0]):
        got = F.conv2d(plane_grid(ones[:, c : c + 1], mask), kernel[:, c : c + 1])[0]
        if not torch.allclose(got, responses[c], rtol=1e-9, atol=1e-9):
            return None
    return kernel


class FoldedBackbone(nn.Module):
    """``backbone(node_tensor(crops, coords))`` rewritten for inference, the same function up to float
    rounding:

    - the /255 of the RGB channels and the first BatchNorm (eval mode: a per-channel affine map) are
      folded into the first convolution's weights and bias;
    - the four coordinate planes are never built. They are constant per object, so their share of the
      first convolution is a 2x2 convolution of the four coordinates on a (OH+1) x (OW+1) grid
      (``corner_kernel``; the default 56 x 56 crops: 29 x 29 grid values instead of 4 x 56 x 56 plane
      pixels, and a 3-channel instead of a 7-channel convolution). onnxruntime adds one convolution's
      output inside the other's blocked (NCHWc) kernel together with the ReLU, provided the graph's shape
      annotations show both have the same object dimension (``name_object_dims``). Measured, one thread,
      the default network on the bench inputs, two interleaved A/B runs: -6 to -10 % at batch 1, -21 to -23 %
      at batch 10. Where no 2x2 kernel reproduces the border (``ResNet18``'s 7x7 / 2 stem with padding 3),
      the planes are concatenated to the crops as before: their response as a matmul added after the
      convolution was slower (16-18 ms vs 14.3 ms, 133 objects; the add stays outside the blocked
      convolution there).

    Backbones: any that declares its first convolution (``stages.relation.backbones.FirstConv``: ``first_conv``,
    ``first_norm``, ``after_first_conv``; ``supports``)."""

    def __init__(self, backbone: nn.Module, input_size: int):
        super().__init__()
        if not self.supports(backbone):
            raise TypeError(f"FoldedBackbone: {type(backbone).__name__} does not declare its first convolution "
                            "(stages.relation.backbones.FirstConv)")
        conv, bn = backbone.first_conv, backbone.first_norm
        self.backbone = backbone   # after_first_conv: the rest of its forward
        self.stride, self.padding = conv.stride, conv.padding
        with torch.no_grad():
            if bn is None:   # the convolution alone: its own bias, if any
                scale = torch.ones(conv.out_channels, dtype=conv.weight.dtype)
                shift = conv.bias if conv.bias is not None else torch.zeros(conv.out_channels)
            else:
                scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
                shift = bn.bias - bn.running_mean * scale
                if conv.bias is not None:
                    shift = shift + conv.bias * scale
            weight = conv.weight * scale[:, None, None, None]
            weight[:, :3] /= 255.0  # the RGB channels arrive as 0..255
            self.register_buffer("bias", shift.clone())
            responses = plane_responses(weight[:, 3:], input_size, self.stride, self.padding)
            kernel = corner_kernel(responses)
        self.on_grid = kernel is not None
        if self.on_grid:
            self.register_buffer("weight", weight[:, :3].clone())
            self.register_buffer("plane_kernel", kernel.to(torch.float32))
            self.register_buffer("grid_mask", grid_mask(responses.shape[-2:]))
        else:
            self.register_buffer("weight", weight)

    @staticmethod
    def supports(backbone: nn.Module) -> bool:
        """Whether ``backbone`` declares a first convolution of the 7 node-tensor channels, 2D, ungrouped."""
        conv = getattr(backbone, "first_conv", None)
        return (isinstance(backbone, FirstConv) and isinstance(conv, nn.Conv2d) and conv.in_channels == IN_CHANNELS
                and conv.groups == 1 and conv.padding_mode == "zeros" and isinstance(conv.padding, tuple)
                and isinstance(backbone.first_norm, nn.BatchNorm2d | None))

    def first_layer(self, crops: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """The folded first convolution (before its ReLU): crops (M, 3, S, S) uint8, coords (M, 4) float."""
        rgb = crops.to(torch.float32)
        if self.on_grid:
            planes = F.conv2d(plane_grid(coords, self.grid_mask), self.plane_kernel)
            return F.conv2d(rgb, self.weight, self.bias, self.stride, self.padding) + planes
        planes = coords[..., None, None].expand(*coords.shape, *crops.shape[-2:])
        return F.conv2d(torch.cat([rgb, planes], dim=1), self.weight, self.bias, self.stride, self.padding)

    def forward(self, crops: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """crops (M, 3, S, S) uint8, coords (M, 4) -> (M, hidden)."""
        return self.backbone.after_first_conv(self.first_layer(crops, coords.to(torch.float32)))


class ShippedRelation(nn.Module):
    """What the relation ONNX models compute: ``RelationGraph`` with ``FoldedBackbone`` (when the backbone
    has a folding) and the graph part channels-first (``ChannelsFirstGraph``). ``real_only`` (the dynamic
    variant): the backbone, most of the cost, runs only on real objects, gathered by their non-zero
    coordinates (``pad_graphs`` pads with all-zero boxes), and padded nodes get zero features. Padding is
    masked out of every output that counts (no edges, not a candidate: ``stages.export.parity``), so a
    batch of images padded to its largest costs the backbone only its real objects. The static variant
    keeps static shapes throughout (no NonZero) for embedded runtimes, so it runs the backbone on every
    slot."""

    def __init__(self, net: nn.Module, real_only: bool):
        super().__init__()
        self.net, self.real_only = net, real_only
        self.graph = ChannelsFirstGraph(net)
        self.folded = FoldedBackbone.supports(net.backbone)
        self.backbone = FoldedBackbone(net.backbone, net.cfg.input_size) if self.folded else None
        if not self.folded:
            log.warning("export: the relation backbone %s does not declare its first convolution "
                        "(stages.relation.backbones.FirstConv): exported without folding the input normalisation "
                        "into it, and the coordinate planes built in full (export.relation.folded_first_conv = 0)",
                        type(net.backbone).__name__)

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
        return self.graph(h.view(b, n, -1), adj, cand, coords.to(torch.float32))


class DetectorGraph(nn.Module):
    """What the detector ONNX model computes: heads and decoded top-K detections in input pixels."""

    def __init__(self, net: nn.Module, k: int):
        super().__init__()
        self.net, self.k = net, k

    def forward(self, images):
        heads = self.net(images)
        return *heads, self.net.decode(heads, self.k)


def name_object_dims(model):
    """The ONNX model with every intermediate tensor's shape annotated, unknown sizes named by where they
    come from (onnxruntime's symbolic shape inference). The tracer leaves the backbone's object dimension
    (objects gathered by NonZero, or batch x max_objects) unnamed, so onnxruntime sees two convolution
    outputs of unknown, possibly different, sizes and will not add one inside the other's blocked kernel
    (``FoldedBackbone``); named, the add and the ReLU run inside the RGB convolution. Shapes only: the
    operations are unchanged."""
    from onnxruntime.tools.symbolic_shape_infer import SymbolicShapeInference

    return SymbolicShapeInference.infer_shapes(model, auto_merge=True)


def _export(module: nn.Module, args: tuple, path: Path, input_names, output_names, dynamic_axes,
            annotate=None) -> Path:
    import onnx

    module.eval()
    with warnings.catch_warnings():  # the tracer warns about every shape it reads; the parity check decides
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, str(path), dynamo=False, opset_version=OPSET, do_constant_folding=True,
                          input_names=list(input_names), output_names=list(output_names),
                          dynamic_axes=dynamic_axes)
    model = onnx.load(str(path))
    if annotate is not None:
        model = annotate(model)
        onnx.save(model, str(path))
    onnx.checker.check_model(model, full_check=True)
    return path


class ShippedEnsemble(nn.Module):
    """``ShippedRelation`` of every member of a ``RelationEnsemble``, outputs averaged: one ONNX graph, so a
    runtime reads an ensemble like a single network."""

    def __init__(self, ensemble: nn.Module, real_only: bool):
        super().__init__()
        self.members = nn.ModuleList(ShippedRelation(m, real_only) for m in ensemble.members)

    def forward(self, crops, coords, adj, cand):
        return mean_outputs([m(crops, coords, adj, cand) for m in self.members])


def folds_first_conv(net: nn.Module) -> bool:
    """Whether the export folds the input normalisation into the first convolution of ``net``'s backbone (every
    member's, for a ``RelationEnsemble``): ``FoldedBackbone.supports``."""
    members = net.members if isinstance(net, RelationEnsemble) else [net]
    return all(FoldedBackbone.supports(m.backbone) for m in members)


def shipped_relation(net: nn.Module, real_only: bool) -> nn.Module:
    """What is exported for ``net``: ``ShippedRelation``, or ``ShippedEnsemble`` for a ``RelationEnsemble``."""
    return ShippedEnsemble(net, real_only) if isinstance(net, RelationEnsemble) else ShippedRelation(net, real_only)


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
    shipped = shipped_relation(net.eval(), real_only=not static)
    return _export(shipped, example, path, RELATION_INPUTS, RELATION_OUTPUTS, axes, annotate=name_object_dims)


def export_facing(net: nn.Module, path: Path, input_size: int) -> Path:
    """Export the facing network: uint8 crops (batch dynamic) -> facing vectors in crop pixels."""
    from deepword.inference.facing_net import FACING_INPUT, FACING_OUTPUT

    example = torch.randint(0, 256, (2, 3, input_size, input_size), dtype=torch.uint8,
                            generator=torch.Generator().manual_seed(0))
    return _export(net, (example,), path, [FACING_INPUT], [FACING_OUTPUT],
                   {FACING_INPUT: {0: "vehicles"}, FACING_OUTPUT: {0: "vehicles"}})


def export_detector(net: nn.Module, path: Path, input_width: int, input_height: int, k: int) -> Path:
    example = (torch.zeros((2, 3, input_height, input_width)),)
    outputs = detector_outputs(net.heads.regression, net.heads.has_facing)
    axes = {DETECTOR_INPUT: {0: "batch"}, **{name: {0: "batch"} for name in outputs}}
    return _export(DetectorGraph(net, k), example, path, (DETECTOR_INPUT,), outputs, axes)

