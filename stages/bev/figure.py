"""Top-view figures in the style of the paper's Fig. 1: the ego (the outline of its camera rig), true
footprints (green), estimated footprints (orange; a line marks the axis), wheel contact points (dots)."""

from __future__ import annotations

import cv2
import numpy as np

from stages.format_3d import Box3D

TRUE_RGB = (40, 170, 60)
ESTIMATE_RGB = (235, 120, 20)
EGO_RGB = (70, 90, 200)
WHEEL_RGB = (200, 0, 200)
GRID_RGB = (225, 225, 225)


def top_view(truth: list[Box3D], estimates: list[Box3D], contacts: np.ndarray, rig_xy: np.ndarray,
             title: str, half_extent_m: float = 14.0, size_px: int = 420) -> np.ndarray:
    """An RGB top view centred on the ego: x forward is up, y left is left."""
    img = np.full((size_px + 24, size_px, 3), 255, np.uint8)
    scale = size_px / (2 * half_extent_m)
    centre = np.mean(rig_xy, axis=0) if len(rig_xy) else np.zeros(2)

    def px(xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - centre
        return np.stack([size_px / 2 - xy[:, 1] * scale, 24 + size_px / 2 - xy[:, 0] * scale], 1)

    def poly(points, colour, thick):
        cv2.polylines(img, [np.round(px(points) * 16).astype(np.int32)], True, colour, thick, cv2.LINE_AA, shift=4)

    for r in range(5, int(half_extent_m * 1.5) + 1, 5):  # range rings every 5 m around the rig
        c = px(centre)[0]
        cv2.circle(img, (int(c[0]), int(c[1])), int(r * scale), GRID_RGB, 1, cv2.LINE_AA)
    if len(rig_xy) >= 2:
        lo, hi = rig_xy.min(axis=0), rig_xy.max(axis=0)
        ego = np.array([[hi[0], hi[1]], [hi[0], lo[1]], [lo[0], lo[1]], [lo[0], hi[1]]])
        cv2.fillPoly(img, [np.round(px(ego) * 16).astype(np.int32)], EGO_RGB, cv2.LINE_AA, shift=4)
    elif len(rig_xy) == 1:  # a single camera: its position
        c = px(rig_xy)[0]
        cv2.circle(img, (int(c[0]), int(c[1])), 5, EGO_RGB, -1, cv2.LINE_AA)
    for b in truth:
        poly(b.corners(), TRUE_RGB, 2)
    for b in estimates:
        poly(b.corners(), ESTIMATE_RGB, 1)
        axis = np.array([np.cos(b.yaw), np.sin(b.yaw)]) * b.length / 2
        ends = px([[b.x, b.y] - axis, [b.x, b.y] + axis]).astype(int)
        cv2.line(img, tuple(ends[0]), tuple(ends[1]), ESTIMATE_RGB, 1, cv2.LINE_AA)
    for c in px(contacts) if len(contacts) else []:
        cv2.circle(img, (int(c[0]), int(c[1])), 2, WHEEL_RGB, -1, cv2.LINE_AA)
    cv2.putText(img, title, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img
