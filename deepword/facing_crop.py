"""Facing vectors between an image and a vehicle box's crop: a crop squeezes its box (grown by a margin on each side)
to a square, so a direction in the crop is not the same direction in the image. The facing network learns and answers
in crop pixels: the facing stage trains on ``to_crop`` of each vehicle's image direction (``deepword.facing``), and
the network's runtime (``deepword.inference.facing_net``) turns its answers back with ``to_image``, their length, the
network's certainty, kept.

A module of its own, numpy only, so that the facing stage's code version holds neither the network's runtime (whose
imports reach the footprints and the inference code: their edits would retrain the network) nor more of
``deepword.facing`` than the targets (that module is in the detector's and the evaluation's code versions too).
"""

from __future__ import annotations

import numpy as np


def grown_sizes(xyxy: np.ndarray, margin: float) -> np.ndarray:
    """(N, 2) width and height of each box grown by ``margin`` x its size on each side: what its crop squeezes."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    wh = np.maximum(xyxy[:, 2:] - xyxy[:, :2], 1e-6)
    return wh * (1 + 2 * margin)


def to_crop(vectors: np.ndarray, xyxy: np.ndarray, margin: float) -> np.ndarray:
    """Image directions (N, 2) of the boxes ``xyxy`` as unit directions in their square crops."""
    v = np.asarray(vectors, dtype=np.float64) / grown_sizes(xyxy, margin)
    return (v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def to_image(vectors: np.ndarray, xyxy: np.ndarray, margin: float) -> np.ndarray:
    """Crop vectors (N, 2) as image vectors: the image direction, the crop vector's length."""
    v = np.asarray(vectors, dtype=np.float64)
    d = v * grown_sizes(xyxy, margin)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return (d * np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)
