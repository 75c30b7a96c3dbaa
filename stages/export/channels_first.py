"""The relation network's graph part (``RelationNet.relate``) with every pair tensor laid out channels-first,
(B, C, N, N), for the exported ONNX graph.

Why: ``relate`` builds its pair tensors (B, N, N, C) (the pair geometry, the GAT's hidden pair features,
the geometry gate's MLP), so its element-wise ops broadcast over short last axes (C = 1, 8, 64), and
onnxruntime runs a broadcast element-wise op as one kernel call per run of the last axis: an Add
(10, 23, 23, 1) + (1,) takes 36 us against 4 us for (10, 23, 23) + (1,) (one thread; 240 vs 23 us on a slower
host). Channels-first, the last axis is the N objects and the per-channel maps are 1x1 convolutions, which
onnxruntime runs as one GEMM.

``ChannelsFirstGraph`` is the same function as ``RelationNet.relate`` in another layout (equal up to float
rounding: the 1x1 convolutions sum in another order than the Linear layers), on the same parameters (it
copies none), and ends in the same ``RelationNet.readout``. The export stage exports it in place of
``relate``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from stages.relation.model import RelationNet, neighbour_softmax


def pair_geometry_channels_first(coords: torch.Tensor) -> torch.Tensor:
    """``pair_geometry`` channels-first: normalised boxes (B, N, 4) -> (B, 8, N, N), [b, :, i, j] = box j
    seen from box i, the same values as ``pair_geometry(coords).permute(0, 3, 1, 2)`` (the same ops, clamps
    and eps, on coords transposed to (B, 4, N): (B, ., N, 1) is box i, (B, ., 1, N) box j)."""
    eps = 1e-6
    c = coords.transpose(1, 2)                                           # (B, 4, N)
    top_left, bottom_right = c[:, :2], c[:, 2:]
    wh = (bottom_right - top_left).clamp_min(eps)                        # (B, 2, N)
    edges = (c.unsqueeze(2) - c.unsqueeze(3)) / torch.cat([wh, wh], 1).unsqueeze(3)
    log_ratio = torch.log(wh.unsqueeze(2) / wh.unsqueeze(3))
    overlap = (torch.minimum(bottom_right.unsqueeze(2), bottom_right.unsqueeze(3))
               - torch.maximum(top_left.unsqueeze(2), top_left.unsqueeze(3))).clamp_min(0)
    inter = overlap[:, 0] * overlap[:, 1]                                # (B, N, N)
    area = wh[:, 0] * wh[:, 1]                                           # (B, N)
    shares = torch.stack([inter / area.unsqueeze(2), inter / area.unsqueeze(1)], 1)  # of i's / of j's area
    return torch.cat([edges.clamp(-10, 10), log_ratio.clamp(-5, 5), shares], 1)


def _conv1x1(x: torch.Tensor, linear: nn.Linear, weight: torch.Tensor | None = None,
             bias: bool = True) -> torch.Tensor:
    """``linear`` (or its columns ``weight``) applied to the channels of x (B, C, N, N) as a 1x1 convolution."""
    weight = linear.weight if weight is None else weight
    return F.conv2d(x, weight[..., None, None], linear.bias if bias else None)


class ChannelsFirstGraph(nn.Module):
    """``net.relate(h, adj, cand, coords)`` with the pair tensors (B, C, N, N): h (B, N, hidden) backbone
    features, adj and cand (B, N, N), coords (B, N, 4) normalised boxes (may be None when the network uses
    no geometry). Returns (owner_scores, couple_scores, front) as ``relate``. Registers no parameters of
    its own: ``net`` is a submodule, its weights are reshaped into convolution kernels inside ``forward``."""

    def __init__(self, net: RelationNet):
        super().__init__()
        self.net = net

    def attention(self, h: torch.Tensor, neighbours: torch.Tensor, geometry: torch.Tensor | None) -> torch.Tensor:
        """``EdgeAttention.forward`` channels-first: Scale (B, N, N) from h (B, N, hidden), geometry (B, 8, N, N)."""
        att = self.net.attention
        w_i, w_j = att.fc1.weight[:, : att.dim], att.fc1.weight[:, att.dim : 2 * att.dim]
        pair = (F.linear(h, w_i, att.fc1.bias).transpose(1, 2).unsqueeze(3)      # (B, hidden_gat, N, 1)
                + F.linear(h, w_j).transpose(1, 2).unsqueeze(2))                 # (B, hidden_gat, 1, N)
        if att.edge_geometry:
            pair = pair + _conv1x1(geometry, att.fc1, att.fc1.weight[:, 2 * att.dim :], bias=False)
        logits = _conv1x1(F.relu(pair), att.fc2).squeeze(1)                       # (B, N, N)
        return neighbour_softmax(logits, neighbours)

    def gate(self, geometry: torch.Tensor) -> torch.Tensor:
        """``GeometryGate.forward`` channels-first: its MLP as 1x1 convolutions over geometry (B, 8, N, N)."""
        f = geometry
        for layer in self.net.gate.net:
            f = _conv1x1(f, layer) if isinstance(layer, nn.Linear) else layer(f)
        f = f.squeeze(1)                                                          # (B, N, N)
        return torch.sigmoid(f + f.transpose(1, 2))

    def forward(self, h: torch.Tensor, adj: torch.Tensor, cand: torch.Tensor, coords: torch.Tensor | None = None):
        net = self.net
        geometry = net.geometry(coords, pairs=pair_geometry_channels_first)
        weights, _ = net.edge_weights(h, adj, geometry, attention=self.attention)
        return net.readout(h, weights, cand, self.gate(geometry) if net.gate is not None else None)
