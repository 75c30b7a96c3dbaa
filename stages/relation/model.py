"""The DeepWORD relation network as a plain torch module (docs/design.md §6), written to export to ONNX.

    x (B, N, 7, S, S) --backbone--> h (B, N, H) --GAT re-weighting of adj (Eq. 3-5)--> W'
    --residual graph convolution (W' row-normalised)--> node features --two heads--> L2-normalised embeddings
    --> cosine scores: ownership (wheel-vehicle pairs) and couples (wheel-wheel pairs); a role head
    gives each wheel's probability of being a front wheel (orders predicted couples rear -> front).
    Optionally (``geometry_gate``, an addition) a learned gate of the pair's relative box geometry
    multiplies the ownership cosines.

Two embedding heads, because one cosine space cannot hold both relations: if two wheels both had
cosine 1 with their vehicle they would have cosine 1 with each other, yet two wheels of one vehicle on
different sides are not a couple. No data-dependent control flow and no boolean indexing in
``forward``: padding and masking are multiplications, so static and dynamic object counts export alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from stages.relation.backbone_spec import CONV_FC, TARGET, legacy_backbone
from stages.relation.backbones import build_backbone

_MASKED_LOGIT = -1e9  # softmax logit of a non-neighbour: exp underflows to exactly 0


# --- graph part ---------------------------------------------------------------------------------------

EDGE_FEATURES = 8  # pair_geometry's width


def pair_geometry(coords: torch.Tensor) -> torch.Tensor:
    """Relative box geometry of every node pair from the normalised boxes (B, N, 4) -> (B, N, N, 8); for
    [b, i, j], box j seen from box i: the offsets of j's left, top, right and bottom edges from i's in units
    of i's width/height (a wheel's bottom is level with its vehicle box's bottom, near its left or right
    end: the cues that tell a near vehicle from the one behind it), log width and height ratios, and the
    share of each box's area inside the other (containment: a wheel sits in its vehicle's box). A few
    broadcast tensor ops, so it traces to a short ONNX graph for any N. Padded nodes (all-zero boxes)
    give finite values; their edges are masked anyway."""
    eps = 1e-6
    top_left, bottom_right = coords[..., :2], coords[..., 2:]
    wh = (bottom_right - top_left).clamp_min(eps)                       # (B, N, 2)
    edges = (coords.unsqueeze(1) - coords.unsqueeze(2)) / torch.cat([wh, wh], -1).unsqueeze(2)
    log_ratio = torch.log(wh.unsqueeze(1) / wh.unsqueeze(2))
    overlap = (torch.minimum(bottom_right.unsqueeze(1), bottom_right.unsqueeze(2))
               - torch.maximum(top_left.unsqueeze(1), top_left.unsqueeze(2))).clamp_min(0)
    inter = overlap[..., 0] * overlap[..., 1]
    area = wh[..., 0] * wh[..., 1]
    shares = torch.stack([inter / area.unsqueeze(2), inter / area.unsqueeze(1)], -1)  # of i's / of j's area
    return torch.cat([edges.clamp(-10, 10), log_ratio.clamp(-5, 5), shares], -1)


def neighbour_softmax(logits: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """Eq. 4: softmax of the edge logits (B, N, N) over each node's neighbours (bool (B, N, N))."""
    logits = torch.where(neighbours, logits, torch.full_like(logits, _MASKED_LOGIT))
    # a node without neighbours (padding) gets a uniform row from softmax: zero it
    return torch.softmax(logits, dim=-1) * neighbours.to(logits.dtype)


def row_normalised(weights: torch.Tensor) -> torch.Tensor:
    """Edge weights (B, N, N) divided by their row sums (an empty row, a padded node, stays zero)."""
    return weights / weights.sum(dim=-1, keepdim=True).clamp_min(1e-12)


class EdgeAttention(nn.Module):
    """Eq. 3-5: e_ij = FC(ReLU(FC(concat(x_i, x_j)))), Scale_ij = softmax of e_ij over i's neighbours.
    The first FC on the concatenation is split into its x_i and x_j halves (the same linear map) so the
    (B, N, N, 2H) concatenation is never built.

    ``edge_geometry`` (an addition to the paper, off = the paper's Net): the first FC also sees the
    pair's relative box geometry (``pair_geometry``), i.e. FC(concat(x_i, x_j, g_ij)). The node features
    hold each box's absolute position only through the coordinate planes, so comparing two boxes (is
    this wheel inside that vehicle, in its lower half?) must otherwise be learned from two embeddings."""

    def __init__(self, dim: int, hidden: int, edge_geometry: bool = False):
        super().__init__()
        self.fc1 = nn.Linear(2 * dim + (EDGE_FEATURES if edge_geometry else 0), hidden)
        self.fc2 = nn.Linear(hidden, 1)
        self.dim = dim
        self.edge_geometry = edge_geometry

    def forward(self, h: torch.Tensor, neighbours: torch.Tensor, geometry: torch.Tensor | None = None) -> torch.Tensor:
        w_i, w_j = self.fc1.weight[:, : self.dim], self.fc1.weight[:, self.dim : 2 * self.dim]
        pair = F.linear(h, w_i, self.fc1.bias).unsqueeze(2) + F.linear(h, w_j).unsqueeze(1)  # (B, N, N, hidden)
        if self.edge_geometry:
            if geometry is None:
                raise ValueError("EdgeAttention(edge_geometry=True) needs the pair geometry of the boxes (coords)")
            pair = pair + F.linear(geometry, self.fc1.weight[:, 2 * self.dim :])
        return neighbour_softmax(self.fc2(F.relu(pair)).squeeze(-1), neighbours)


class GeometryGate(nn.Module):
    """An addition to the paper: gate_ij = sigmoid(f(g_ij) + f(g_ji)), f a small MLP of the pair's
    relative box geometry (``pair_geometry``); it multiplies the ownership cosines. The cosine of two
    embeddings says how alike a wheel and a vehicle look after message passing; it cannot compare the two
    boxes directly, and a small wheel inside two overlapping vehicle boxes looks alike to both: whose box
    bottom it is level with settles it. Symmetric, like the cosines, and in (0, 1), so scores stay in
    [-1, 1]."""

    def __init__(self, hidden: int = 32):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(EDGE_FEATURES, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def logits(self, geometry: torch.Tensor) -> torch.Tensor:
        """f(g_ij) + f(g_ji), the gate before its sigmoid (B, N, N); the training's gate loss reads it."""
        f = self.net(geometry).squeeze(-1)
        return f + f.transpose(1, 2)

    def forward(self, geometry: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.logits(geometry))


def _default_backbone() -> dict:
    return {TARGET: CONV_FC, "input_size": 56, "expansion": 4}


@dataclass(frozen=True)
class ModelConfig:
    """The relation network's configuration: its backbone node (``_target_`` and the class's keyword arguments:
    ``stages.relation.backbones``) and the graph part's settings. JSON-able (``relation.json``, checkpoints)."""
    backbone: dict = field(default_factory=_default_backbone)
    hidden: int = 128
    embed_dim: int = 64
    gat: bool = True
    gat_hidden: int = 64
    gcn_layers: int = 2
    edge_geometry: bool = False  # addition to the paper: GAT sees the pair's relative box geometry
    geometry_gate: bool = False  # addition to the paper: a learned geometry gate on the ownership cosines

    def __hash__(self) -> int:   # the backbone node is a dict
        return hash(repr(self))

    @property
    def input_size(self) -> int:
        """The crop side S the backbone takes."""
        return int(self.backbone["input_size"])

    @classmethod
    def from_cfg(cls, rel) -> ModelConfig:
        """From the ``relation`` config: the backbone node as it is, the graph part from ``relation.model``."""
        from omegaconf import OmegaConf

        m = rel.model
        return cls(backbone=OmegaConf.to_container(rel.backbone, resolve=True), hidden=int(m.hidden),
                   embed_dim=int(m.embed_dim), gat=bool(m.gat), gat_hidden=int(m.gat_hidden),
                   gcn_layers=int(m.gcn_layers), edge_geometry=bool(m.edge_geometry),
                   geometry_gate=bool(m.geometry_gate))

    @classmethod
    def of(cls, model: dict) -> ModelConfig:
        """From a saved ``asdict(ModelConfig)`` (relation.json's ``model``, a checkpoint's hyper-parameters), including
        one saved before the backbone node named its class (``backbone: conv_fc`` beside ``input_size``,
        ``expansion``, ``base_width``: ``stages.relation.backbone_spec.legacy_backbone``)."""
        model = dict(model)
        if isinstance(model.get("backbone"), str):
            old = {k: model.pop(k) for k in ("input_size", "expansion", "base_width") if k in model}
            model["backbone"] = legacy_backbone(model["backbone"], old)
        return cls(**model)


class RelationNet(nn.Module):
    """Inputs: x (B, N, 7, S, S) node tensors, adj (B, N, N) edge weights (self-loops on valid nodes),
    cand (B, N, N) 0/1 candidate pairs. Outputs: ownership scores (B, N, N), couple scores (B, N, N),
    both cosines multiplied by cand, and front probability (B, N)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone = build_backbone(cfg.backbone, cfg.hidden)
        self.attention = EdgeAttention(cfg.hidden, cfg.gat_hidden, cfg.edge_geometry) if cfg.gat else None
        self.gcn = nn.ModuleList(nn.Linear(cfg.hidden, cfg.hidden) for _ in range(cfg.gcn_layers))
        self.owner_head = nn.Linear(cfg.hidden, cfg.embed_dim)
        self.couple_head = nn.Linear(cfg.hidden, cfg.embed_dim)
        self.role_head = nn.Linear(cfg.hidden, 1)
        self.gate = GeometryGate() if cfg.geometry_gate else None

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """Backbone over every node: (B, N, 7, S, S) -> (B, N, hidden)."""
        b, n = x.shape[0], x.shape[1]
        return self.backbone(x.flatten(0, 1)).reshape(b, n, self.cfg.hidden)

    def edge_weights(self, h: torch.Tensor, adj: torch.Tensor, geometry: torch.Tensor | None = None,
                     attention=None) -> tuple[torch.Tensor, torch.Tensor]:
        """W' = adj * Scale (Eq. 5; Scale = 1 without GAT), row-normalised for the graph convolution so
        that with and without GAT a node's update is a weighted mean of its neighbours. Returns (W', Scale).
        ``geometry`` = ``pair_geometry(coords)``: needed only with ``edge_geometry``. ``attention``: what
        computes Scale with GAT (default ``self.attention``; the export passes its channels-first form)."""
        neighbours = adj > 0
        if self.attention is None:
            scale = neighbours.to(adj.dtype)
        else:
            scale = (self.attention if attention is None else attention)(h, neighbours, geometry)
        return row_normalised(adj * scale), scale

    @property
    def needs_geometry(self) -> bool:
        """Whether ``relate`` needs the boxes (coords): for the geometry gate or the GAT's edge geometry."""
        return self.gate is not None or (self.attention is not None and self.cfg.edge_geometry)

    def geometry(self, coords: torch.Tensor | None, pairs=pair_geometry) -> torch.Tensor | None:
        """``pairs(coords)`` when the network uses the pair geometry (computed once for the GAT and the gate),
        else None; a clear error when it is needed and ``coords`` is missing."""
        if not self.needs_geometry:
            return None
        if coords is None:
            raise ValueError("RelationNet: edge_geometry and geometry_gate need the normalised boxes (coords)")
        return pairs(coords)

    def relate(self, h: torch.Tensor, adj: torch.Tensor, cand: torch.Tensor, coords: torch.Tensor | None = None):
        """Graph part on backbone features h (B, N, hidden) and normalised boxes coords (B, N, 4)."""
        geometry = self.geometry(coords)
        weights, _ = self.edge_weights(h, adj, geometry)
        return self.readout(h, weights, cand, self.gate(geometry) if self.gate is not None else None)

    def readout(self, h: torch.Tensor, weights: torch.Tensor, cand: torch.Tensor, gate: torch.Tensor | None):
        """``relate``'s tail: residual graph convolution with the row-normalised edge weights (B, N, N),
        the two embedding heads, their cosines times cand, the ownership cosines times ``gate`` (B, N, N)
        (the geometry gate's output, None without one), and the front probability."""
        for layer in self.gcn:  # residual: a node keeps its own features beside the neighbours' mean
            h = h + F.relu(layer(weights @ h))
        owner = F.normalize(self.owner_head(h), dim=-1)
        couple = F.normalize(self.couple_head(h), dim=-1)
        cand = cand.to(h.dtype)
        owner_scores = (owner @ owner.transpose(1, 2)) * cand
        if gate is not None:
            owner_scores = owner_scores * gate
        couple_scores = (couple @ couple.transpose(1, 2)) * cand
        front = torch.sigmoid(self.role_head(h).squeeze(-1))
        return owner_scores, couple_scores, front

    def forward(self, x: torch.Tensor, adj: torch.Tensor, cand: torch.Tensor):
        # the boxes are the node tensor's constant coordinate planes (channels 3-6), read at one pixel
        return self.relate(self.embed(x), adj, cand, x[:, :, 3:, 0, 0])


class RelationEnsemble(nn.Module):
    """Several RelationNets of one configuration, trained from different seeds, deciding on the mean of
    their scores (``relation.ensemble``): the same inputs and outputs as one RelationNet. One network's
    held-out accuracy swings with its training seed by more than the gaps the report compares; the mean
    of a few is better than the typical member and as steady as the best (docs/domain.md)."""

    def __init__(self, members: list[RelationNet]):
        super().__init__()
        if not members:
            raise ValueError("RelationEnsemble needs at least one member network")
        if any(m.cfg != members[0].cfg for m in members):
            raise ValueError("RelationEnsemble: the member networks differ in configuration")
        self.members = nn.ModuleList(members)

    @property
    def cfg(self) -> ModelConfig:
        return self.members[0].cfg

    def forward(self, x: torch.Tensor, adj: torch.Tensor, cand: torch.Tensor):
        return mean_outputs([m(x, adj, cand) for m in self.members])


def mean_outputs(outputs: list[tuple[torch.Tensor, ...]]) -> tuple[torch.Tensor, ...]:
    """The element-wise mean of several networks' (owner, couple, front) outputs."""
    return tuple(torch.stack(parts).mean(0) for parts in zip(*outputs, strict=True))


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def size_mb(model: nn.Module) -> float:
    """Parameters and buffers (BN statistics) in MB, as a float32 state_dict holds them."""
    n_bytes = sum(t.numel() * t.element_size() for t in model.state_dict().values())
    return n_bytes / 2**20
