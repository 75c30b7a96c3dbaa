"""Relations of new images from a trained relation stage: the predictor the evaluate stage (and anyone
with boxes and an image) uses. Boxes may be annotated or detected; any object count works (the graph is
padded per batch to its largest image, not to max_objects).

Couples come out rear first: when the training data named roles, the wheel with the lower front
probability (role head) is the rear one and every assigned wheel gets a role; without roles in the
training data the left wheel (smaller centre x) is listed first and roles stay empty.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from deepword.inference.decode import prediction_record
from deepword.priors import load_priors
from deepword.relation_graph import ImageGraph, InputConfig, build_graph, node_tensor
from deepword.word_format import Record


class RelationPredictor:
    """A trained RelationNet with the input settings and priors it was trained with."""

    def __init__(self, net, meta: dict, priors):
        self.net = net.eval()
        self.meta = meta
        self.inputs = InputConfig(**meta["inputs"])
        self.threshold = float(meta["decode"]["threshold"])
        self.one_owner = bool(meta["decode"]["one_owner"])
        self.min_containment = float(meta["decode"].get("min_containment", 0.0))
        self.has_roles = bool(meta["has_roles"])
        self.priors = priors

    @classmethod
    def from_dirs(cls, relation_dir: str | os.PathLike, priors_dir: str | os.PathLike) -> RelationPredictor:
        # imported here: it loads torch, which importing this module must not
        from stages.relation.stage import load_network

        net, meta = load_network(Path(relation_dir))
        return cls(net, meta, load_priors(priors_dir))

    def graph(self, rec: Record, rgb: np.ndarray) -> ImageGraph:
        return build_graph(rec, rgb, self.inputs, self.priors.wheel_vehicle, self.priors.wheel_wheel)

    def scores(self, graphs: Sequence[ImageGraph]):
        """Ownership and couple scores (B, N, N) and front probabilities (B, N), N = largest graph."""
        import torch

        n = max([len(g.classes) for g in graphs] + [1])
        size = self.inputs.input_size
        b = len(graphs)
        crops = torch.zeros((b, n, 3, size, size), dtype=torch.uint8)
        coords = torch.zeros((b, n, 4))
        adj = torch.zeros((b, n, n))
        cand = torch.zeros((b, n, n))
        classes = torch.full((b, n), -1, dtype=torch.long)
        for i, g in enumerate(graphs):
            k = len(g.classes)
            crops[i, :k], coords[i, :k] = torch.from_numpy(g.crops), torch.from_numpy(g.coords)
            adj[i, :k, :k], cand[i, :k, :k] = torch.from_numpy(g.adj), torch.from_numpy(g.cand.astype(np.float32))
            classes[i, :k] = torch.from_numpy(g.classes.astype(np.int64))
        with torch.no_grad():
            owner, couple, front = self.net(node_tensor(crops, coords), adj, cand)
        return owner, couple, front, classes, cand, coords

    def predict_many(self, records: Sequence[Record], load_rgb: Callable[[Record], np.ndarray],
                     batch_size: int = 16) -> list[Record]:
        # imported here: it loads torch, which importing this module must not
        from stages.relation.decode import decode_couples, decode_owners

        out = []
        for start in range(0, len(records), batch_size):
            chunk = records[start:start + batch_size]
            graphs = [self.graph(rec, load_rgb(rec)) for rec in chunk]
            owner, couple, front, classes, cand, coords = self.scores(graphs)
            pred_owner = decode_owners(owner, classes, cand, self.threshold, self.one_owner, coords,
                                       self.min_containment)
            pred_couple = decode_couples(couple, classes, cand, self.threshold)
            for i, rec in enumerate(chunk):
                out.append(prediction_record(rec, pred_owner[i].numpy(), pred_couple[i].numpy(), front[i].numpy(),
                                             self.has_roles))
        return out

    def predict(self, rec: Record, rgb: np.ndarray) -> Record:
        return self.predict_many([rec], lambda _: rgb)[0]
