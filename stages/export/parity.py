"""Parity of an exported model with the PyTorch network it came from, on the same inputs.

Two figures per model: the largest absolute difference of any output that matters, and the share (in
percent) of decisions that agree. For the relation network, "what matters" is the score of every
candidate pair (valid nodes; padding is multiplied away in both) and the front probability of every
valid wheel, and a decision is "score > threshold" of a candidate pair. For the detector it is the three
heads (relative beyond magnitude 1: ``head_difference``), and a decision is "heatmap >= score threshold" of a cell and class (the decoding in the graph,
peak extraction and top-K, is then the same computation on the same heads; comparing its output slot by
slot would count two near-equal peaks listed in the other order as a disagreement).
An export that misses the tolerances must not ship: ``ParityReport.check`` raises.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deepword.inference.runtime import DETECTOR_INPUT, RELATION_OUTPUTS, pad_graphs


class ParityError(RuntimeError):
    """An exported model disagrees with PyTorch beyond the configured tolerance."""


@dataclass
class ParityReport:
    max_abs_diff: float = 0.0
    agreeing: int = 0
    decisions: int = 0

    @property
    def decision_agreement(self) -> float:
        """Percent of decisions identical in both; 100 when there was nothing to decide."""
        return 100.0 * self.agreeing / self.decisions if self.decisions else 100.0

    def add(self, diff: float, agreeing: int, decisions: int) -> None:
        self.max_abs_diff = max(self.max_abs_diff, float(diff))
        self.agreeing += int(agreeing)
        self.decisions += int(decisions)

    def check(self, what: str, max_abs_diff: float, min_agreement: float) -> None:
        if not self.max_abs_diff <= max_abs_diff or self.decision_agreement < min_agreement:
            raise ParityError(
                f"{what}: onnxruntime differs from PyTorch: max |diff| {self.max_abs_diff:.3g} (allowed "
                f"{max_abs_diff:g}), decisions agree on {self.decision_agreement:.3f} % of {self.decisions} "
                f"(required {min_agreement:g} %)")

    def metrics(self, prefix: str) -> dict[str, float]:
        return {f"{prefix}.parity_max_abs_diff": self.max_abs_diff,
                f"{prefix}.parity_decision_agreement": self.decision_agreement}


def compare_relation(report: ParityReport, ref: Sequence[np.ndarray], got: Sequence[np.ndarray],
                     cand: np.ndarray, classes: np.ndarray, threshold: float) -> None:
    """Add one batch: ``ref``/``got`` are (owner, couple, front) of PyTorch and onnxruntime."""
    pairs = cand > 0
    valid = classes >= 0
    diff = 0.0
    agreeing = decisions = 0
    for r, g in zip(ref[:2], got[:2], strict=True):  # owner, couple scores on candidate pairs
        if pairs.any():
            diff = max(diff, float(np.abs(r[pairs] - g[pairs]).max()))
        agreeing += int(((r[pairs] > threshold) == (g[pairs] > threshold)).sum())
        decisions += int(pairs.sum())
    if valid.any():
        diff = max(diff, float(np.abs(ref[2][valid] - got[2][valid]).max()))
    report.add(diff, agreeing, decisions)


def relation_parity(net, session, graphs: Sequence, input_size: int, threshold: float, n: int | None,
                    batch_size: int = 16) -> ParityReport:
    """Run ``graphs`` through the torch ``RelationGraph``-equivalent network and the ONNX session, padded
    to ``n`` objects (None: each batch's largest graph)."""
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.export.onnx_export import RelationGraph

    graph_net = RelationGraph(net).eval()
    report = ParityReport()
    for start in range(0, len(graphs), batch_size):
        feed, classes = pad_graphs(graphs[start:start + batch_size], input_size, n)
        with torch.no_grad():
            ref = [t.numpy() for t in graph_net(*(torch.from_numpy(feed[k]) for k in feed))]
        got = session.run(list(RELATION_OUTPUTS), feed)
        compare_relation(report, ref, got, feed["cand"], classes, threshold)
    return report


def head_difference(ref: np.ndarray, got: np.ndarray) -> np.ndarray:
    """Absolute difference where an output is at most 1 in magnitude (heatmap, offsets), relative beyond:
    the size head is in pixels, and float32 rounding of a 100 px box is ~1e-5 px, so an absolute 1e-4
    fails a trained detector for rounding alone while its decisions all agree."""
    return np.abs(ref - got) / np.maximum(1.0, np.abs(ref))


def compare_detector(report: ParityReport, ref: Sequence[np.ndarray], got: Sequence[np.ndarray],
                     score_threshold: float) -> None:
    """Add one batch: (heatmap, regression maps..., detections) of PyTorch and onnxruntime; every output but
    the decoded detections is compared. Decisions are per heatmap cell and class (score >= threshold), which
    do not depend on how top-K orders near-equal peaks."""
    diff = max(float(head_difference(r, g).max()) for r, g in zip(ref[:-1], got[:-1], strict=True))
    same = (ref[0] >= score_threshold) == (got[0] >= score_threshold)
    report.add(diff, int(same.sum()), same.size)


def detector_parity(net, session, images: np.ndarray, k: int, score_threshold: float,
                    batch_size: int = 8) -> ParityReport:
    """``images`` (I, 3, H, W) network inputs through the torch ``DetectorGraph`` and the ONNX session."""
    import torch

    # imported here: it loads torch, which importing this module must not
    from stages.export.onnx_export import DetectorGraph

    graph_net = DetectorGraph(net, k).eval()
    report = ParityReport()
    for start in range(0, len(images), batch_size):
        x = np.ascontiguousarray(images[start:start + batch_size])
        with torch.no_grad():
            ref = [t.numpy() for t in graph_net(torch.from_numpy(x))]
        compare_detector(report, ref, session.run(None, {DETECTOR_INPUT: x}), score_threshold)
    return report
