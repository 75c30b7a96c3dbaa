"""Eq. 1-2 of DeepWORD: normalised centre distance and distance ratio of box pairs, vectorised.

The single source of truth for this geometry: priors, the relation network's adjacency and the logic
models all call these functions. For a pair (A, B) -- A the vehicle and B the wheel, or A the rear and B
the front wheel -- with image size W x H and B's box size w_B x h_B:

    D^2   = ((A_x - B_x) / W)^2 + ((A_y - B_y) / H)^2
    ratio = 2 D / (w_B / W + h_B / H)
"""

from __future__ import annotations

import numpy as np


def box_centres(xyxy: np.ndarray) -> np.ndarray:
    """(..., 4) boxes x1, y1, x2, y2 -> (..., 2) centres."""
    xyxy = np.asarray(xyxy, dtype=np.float64)
    return np.stack([(xyxy[..., 0] + xyxy[..., 2]) / 2, (xyxy[..., 1] + xyxy[..., 3]) / 2], axis=-1)


def normalised_distance(a_xyxy: np.ndarray, b_xyxy: np.ndarray, width: float, height: float) -> np.ndarray:
    """Eq. 1: D between the centres of A and B, coordinates normalised by image width and height.
    Broadcasts: (N, 4) against (M, 4) given as a[:, None] and b[None] yields (N, M)."""
    ca, cb = box_centres(a_xyxy), box_centres(b_xyxy)
    dx = (ca[..., 0] - cb[..., 0]) / width
    dy = (ca[..., 1] - cb[..., 1]) / height
    return np.sqrt(dx * dx + dy * dy)


def distance_ratio(a_xyxy: np.ndarray, b_xyxy: np.ndarray, width: float, height: float) -> np.ndarray:
    """Eq. 2: 2 D / (w_B / W + h_B / H) -- the centre distance in units of B's normalised size."""
    b = np.asarray(b_xyxy, dtype=np.float64)
    size = (b[..., 2] - b[..., 0]) / width + (b[..., 3] - b[..., 1]) / height
    return 2.0 * normalised_distance(a_xyxy, b_xyxy, width, height) / size


def pairwise_distance_ratio(a_xyxy: np.ndarray, b_xyxy: np.ndarray, width: float, height: float) -> np.ndarray:
    """Ratio for every (A_i, B_j) combination: (N, 4), (M, 4) -> (N, M)."""
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    return distance_ratio(a[:, None, :], b[None, :, :], width, height)


def pairwise_iou(a_xyxy: np.ndarray, b_xyxy: np.ndarray) -> np.ndarray:
    """Intersection over union of every (A_i, B_j): (N, 4), (M, 4) -> (N, M)."""
    inter = pairwise_intersection(a_xyxy, b_xyxy)
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def pairwise_intersection(a_xyxy: np.ndarray, b_xyxy: np.ndarray) -> np.ndarray:
    """Intersection area of every (A_i, B_j): (N, 4), (M, 4) -> (N, M)."""
    a = np.asarray(a_xyxy, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b_xyxy, dtype=np.float64).reshape(-1, 4)
    w = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    h = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    return np.clip(w, 0, None) * np.clip(h, 0, None)


def containment(inner_xyxy: np.ndarray, outer_xyxy: np.ndarray) -> np.ndarray:
    """Share of each inner box's area that lies inside each outer box: (N, 4), (M, 4) -> (N, M)."""
    inner = np.asarray(inner_xyxy, dtype=np.float64).reshape(-1, 4)
    area = (inner[:, 2] - inner[:, 0]) * (inner[:, 3] - inner[:, 1])
    return pairwise_intersection(inner, outer_xyxy) / np.maximum(area[:, None], 1e-12)
