"""The shipped relation model's scores on many subsets of each image's boxes, every box's crop through the
backbone once.

The operating-point search (``deepword.operating_point.search``) runs the relation model on tens of thousands of
subsets of the same val detections (22,836 on the quick profile), and onnxruntime ran the crop backbone, nearly
all of the model's cost, for every kept box of every subset: × the ensemble's members × 2 with flip averaging.
Yet a box's backbone features depend on its own crop and coordinates alone (``ShippedRelation.embed``); only
the graph part sees which other boxes are kept. So each image's boxes, and those of its mirror image, are
embedded once by every member, and a subset costs the graph part alone on the rows of its boxes.

The modules are the ones the ONNX models are exported from (``stages.export.onnx_export.shipped_relation``:
the folded backbone, the channels-first graph part), run by PyTorch in fp32: the same function as the shipped
model up to float rounding, which the export stage checks on the val graphs before the search uses them
(``max_abs_diff_to``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import torch

from deepword.inference.runtime import pad_graphs
from deepword.relation_graph import ImageGraph, mirror_coords, mirrored, subgraph
from stages.relation.model import mean_outputs


class EmbeddedBoxes:
    """``scores`` of subsets of ``graphs`` ({image: the graph of all its detections}) as ``OnnxRelation.scores``
    gives them for the subsets' graphs, from backbone features computed here once per box, member and view."""

    def __init__(self, net: torch.nn.Module, graphs: dict[str, ImageGraph], flip_average: bool, batch_size: int = 256):
        # imported here: it loads torch, which importing this module must not
        from stages.export.onnx_export import ShippedEnsemble, shipped_relation

        shipped = shipped_relation(net.eval(), real_only=True)
        self.members = list(shipped.members) if isinstance(shipped, ShippedEnsemble) else [shipped]
        self.graphs, self.batch_size = graphs, int(batch_size)
        # the views a graph is scored in: as it is, and mirrored with relation.decode.flip_average
        self.mirror = [False, True] if flip_average else [False]
        with torch.no_grad():
            # features[image][view] -> (members, n, hidden)
            self.features = {image: [self._embed(mirrored(g) if m else g) for m in self.mirror]
                             for image, g in graphs.items()}
        # the graphs without their crops (a zero-width stand-in), so that a subset's graph copies no pixels
        self.nodes = {image: replace(g, crops=np.empty((len(g.classes), 0), np.uint8)) for image, g in graphs.items()}

    def _embed(self, graph: ImageGraph) -> torch.Tensor:
        crops = torch.from_numpy(np.ascontiguousarray(graph.crops))
        coords = torch.from_numpy(np.asarray(graph.coords, np.float32))
        if len(crops) == 0:
            return torch.zeros(len(self.members), 0, self.members[0].net.cfg.hidden)
        return torch.stack([m.embed(crops, coords) for m in self.members])

    def scores(self, images: Sequence[str], rows: Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
        """(owner, couple, front, classes, cand, coords) for the graphs of ``graphs[images[i]]`` restricted to its
        nodes ``rows[i]`` (a batch, padded to its largest subset by ``deepword.inference.runtime.pad_graphs``)."""

        feed, classes = pad_graphs([subgraph(self.nodes[image], idx) for image, idx in zip(images, rows, strict=True)],
                                   0, crops=False)
        coords, adj, cand = feed["coords"], feed["adj"], feed["cand"]
        b, n = classes.shape
        h = torch.zeros(len(self.mirror), len(self.members), b, n, self.members[0].net.cfg.hidden)
        for i, (image, idx) in enumerate(zip(images, rows, strict=True)):
            for v in range(len(self.mirror)):
                h[v, :, i, :len(idx)] = self.features[image][v][:, torch.from_numpy(np.asarray(idx, np.int64))]
        mirrored_coords = mirror_coords(coords.reshape(-1, 4)).reshape(coords.shape)
        mirrored_coords[classes < 0] = 0.0  # padding stays all-zero boxes, as the runtime pads mirrored graphs
        adj_t, cand_t = torch.from_numpy(adj), torch.from_numpy(cand)
        outputs = []
        with torch.no_grad():
            for v, mirror in enumerate(self.mirror):
                view_coords = torch.from_numpy(mirrored_coords if mirror else coords)
                outputs.append(mean_outputs([m.graph(h[v, j], adj_t, cand_t, view_coords)
                                             for j, m in enumerate(self.members)]))
        if len(outputs) == 2:  # flip averaging: the mean of the two views, as OnnxRelation.scores takes it
            outputs = [tuple((a + b) / 2 for a, b in zip(*outputs, strict=True))]
        owner, couple, front = outputs[0]
        return owner.numpy(), couple.numpy(), front.numpy(), classes, cand, coords

    def max_abs_diff_to(self, scores: Callable[[list[ImageGraph]], tuple[np.ndarray, ...]]) -> float:
        """The largest difference between ``scores`` (the shipped model's, ``OnnxRelation.scores``) and this
        split's on every whole graph, over the candidate pairs' scores and the front probabilities of real nodes."""
        worst = 0.0
        images = list(self.graphs)
        for start in range(0, len(images), 16):
            chunk = images[start:start + 16]
            rows = [np.arange(len(self.graphs[image].classes)) for image in chunk]
            mine, theirs = self.scores(chunk, rows), scores([self.graphs[image] for image in chunk])
            pairs, nodes = mine[4] > 0, mine[3] >= 0
            for a, b, where in ((mine[0], theirs[0], pairs), (mine[1], theirs[1], pairs), (mine[2], theirs[2], nodes)):
                if where.any():
                    worst = max(worst, float(np.abs(a - b)[where].max()))
        return worst
