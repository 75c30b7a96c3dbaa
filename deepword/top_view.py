"""Top-view figures in the style of the paper's Fig. 1: the ego car (the outline of its camera rig, its nose
forward) with range rings around the vehicle frame's origin, true footprints (green), estimated footprints
coloured by the camera whose estimate leads them (thicker where two or more cameras saw the vehicle; paler the
lower their confidence, ``faded``), each with an arrow to its front where a vote (wheel roles, a facing vector) gave
the direction or a bare axis line where none did, wheel contact points (black dots), and a legend."""

from __future__ import annotations

import cv2
import numpy as np

from deepword.footprint import Estimate, group_confidence, group_directed
from deepword.format_3d import Box3D

TRUE_RGB = (40, 170, 60)
ESTIMATE_RGB = (235, 120, 20)   # an estimate without a known camera
CAMERA_RGB = {"front": (31, 119, 180), "left": (148, 103, 189), "right": (214, 39, 40), "rear": (235, 120, 20)}
EGO_RGB = (95, 95, 95)
WHEEL_RGB = (0, 0, 0)
GRID_RGB = (215, 215, 215)
TEXT_RGB = (60, 60, 60)
TITLE_PX = 24
LEGEND_PX = 56
FONT = cv2.FONT_HERSHEY_SIMPLEX
# Footprints at or above this confidence are drawn in their full colour; below it paler, down to FADED_SHARE of it
# at confidence 0 (a footprint mostly under a more confident one, deepword.footprint.suppress_overlaps, or a no-wheel
# fit that explains its box badly), so the view shows what the AP ranks last. A well-fitted no-wheel estimate on a
# labelled box (0.3 x its fit) stays at full colour.
FULL_CONFIDENCE = 0.2
FADED_SHARE = 0.3


def faded(colour: tuple[int, int, int], confidence: float | None) -> tuple[int, int, int]:
    """``colour`` mixed with white by how far ``confidence`` lies under FULL_CONFIDENCE (None: unchanged)."""
    if confidence is None:
        return colour
    share = FADED_SHARE + (1 - FADED_SHARE) * min(1.0, max(0.0, float(confidence)) / FULL_CONFIDENCE)
    return tuple(int(round(255 - (255 - c) * share)) for c in colour)


def camera_colour(name: str | None) -> tuple[int, int, int]:
    return CAMERA_RGB.get(name or "", ESTIMATE_RGB)


def top_view(truth: list[Box3D], estimates: list[Box3D], contacts: np.ndarray, rig_xy: np.ndarray,
             title: str, half_extent_m: float = 14.0, size_px: int = 420, cameras: list | None = None,
             directed: list[bool] | None = None, seen_by: list[int] | None = None,
             legend: bool = True, confidence: list[float] | None = None) -> np.ndarray:
    """An RGB top view centred on the ego's rig: x forward is up, y left is left. ``cameras``: per estimate the
    camera (name) whose estimate leads it (its colour); ``directed``: per estimate whether its heading points to
    the front (an arrow) or only the axis is known (a line); ``seen_by``: per estimate how many cameras saw it;
    ``confidence``: per estimate its confidence (``faded``)."""
    legend_px = LEGEND_PX if legend else 0
    img = np.full((TITLE_PX + size_px + legend_px, size_px, 3), 255, np.uint8)
    scale = size_px / (2 * half_extent_m)
    centre = np.mean(rig_xy, axis=0) if len(rig_xy) else np.zeros(2)

    def px(xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - centre
        return np.stack([size_px / 2 - xy[:, 1] * scale, TITLE_PX + size_px / 2 - xy[:, 0] * scale], 1)

    def fixed(points) -> np.ndarray:
        return np.round(px(points) * 16).astype(np.int32)

    def poly(points, colour, thick):
        cv2.polylines(img, [fixed(points)], True, colour, thick, cv2.LINE_AA, shift=4)

    origin = px([0.0, 0.0])[0]
    for r in range(5, int(half_extent_m * 1.5) + 1, 5):  # range rings every 5 m around the vehicle frame's origin
        cv2.circle(img, (int(round(origin[0] * 16)), int(round(origin[1] * 16))), int(round(r * scale * 16)),
                   GRID_RGB, 1, cv2.LINE_AA, shift=4)
        label = px([r / np.sqrt(2), -r / np.sqrt(2)])[0]
        if TITLE_PX + 8 < label[1] < TITLE_PX + size_px - 4 and label[0] < size_px - 30:
            cv2.putText(img, f"{r} m", (int(label[0]) + 2, int(label[1]) - 2), FONT, 0.33, (150, 150, 150), 1,
                        cv2.LINE_AA)
    if len(rig_xy) >= 2:
        lo, hi = rig_xy.min(axis=0), rig_xy.max(axis=0)
        lo, hi = lo - 0.15, hi + 0.15
        nose = hi[0] + 0.35
        body = np.array([[hi[0], hi[1]], [nose, (hi[1] + lo[1]) / 2], [hi[0], lo[1]], [lo[0], lo[1]], [lo[0], hi[1]]])
        cv2.fillPoly(img, [fixed(body)], EGO_RGB, cv2.LINE_AA, shift=4)
    elif len(rig_xy) == 1:  # a single camera: its position
        c = px(rig_xy)[0]
        cv2.circle(img, (int(c[0]), int(c[1])), 5, EGO_RGB, -1, cv2.LINE_AA)
    for b in truth:
        poly(b.corners(), TRUE_RGB, 2)
        tip = px([b.x + np.cos(b.yaw) * b.length / 2, b.y + np.sin(b.yaw) * b.length / 2])[0]
        cv2.circle(img, (int(tip[0]), int(tip[1])), 3, TRUE_RGB, -1, cv2.LINE_AA)   # the true front
    for i, b in enumerate(estimates):
        colour = faded(camera_colour(cameras[i] if cameras else None), confidence[i] if confidence else None)
        thick = 2 if seen_by and seen_by[i] > 1 else 1
        poly(b.corners(), colour, thick)
        axis = np.array([np.cos(b.yaw), np.sin(b.yaw)]) * b.length / 2
        if directed and directed[i]:
            ends = px([[b.x, b.y], [b.x, b.y] + axis]).astype(int)
            cv2.arrowedLine(img, tuple(ends[0]), tuple(ends[1]), colour, 1, cv2.LINE_AA, tipLength=0.35)
        else:
            ends = px([[b.x, b.y] - axis, [b.x, b.y] + axis]).astype(int)
            cv2.line(img, tuple(ends[0]), tuple(ends[1]), colour, 1, cv2.LINE_AA)
    for c in px(contacts) if len(contacts) else []:
        cv2.circle(img, (int(c[0]), int(c[1])), 2, WHEEL_RGB, -1, cv2.LINE_AA)
    cv2.putText(img, title, (6, 17), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if legend:
        draw_legend(img, TITLE_PX + size_px, camera_names=[c for c in CAMERA_RGB if not cameras or c in cameras],
                    truth=bool(truth))
    return img


def fused_top_view(truth: list[Box3D], fused: list[tuple[Box3D, list[Estimate]]], contacts: np.ndarray,
                   rig_xy: np.ndarray, title: str, half_extent_m: float = 14.0, size_px: int = 420) -> np.ndarray:
    """``top_view`` of fused footprints (``deepword.footprint.fuse_frame``'s (box, its estimates) pairs), each drawn
    by its group: the leading estimate's camera, whether a vote gave its front, how many cameras saw it, its
    confidence."""
    return top_view(truth, [b for b, _ in fused], contacts, rig_xy, title, half_extent_m, size_px,
                    cameras=[g[0].camera for _, g in fused], directed=[group_directed(g) for _, g in fused],
                    seen_by=[len({e.camera for e in g}) for _, g in fused],
                    confidence=[group_confidence(g) for _, g in fused])


def draw_legend(img: np.ndarray, top: int, camera_names: list[str], truth: bool = True) -> None:
    """Three legend rows under a top view: truth / ego / contacts / arrow-vs-line, the cameras' colours, and what a
    paler footprint means."""
    cv2.line(img, (0, top), (img.shape[1], top), GRID_RGB, 1)
    x, y = 6, top + 14

    def entry(x, label, draw):
        draw(x)
        cv2.putText(img, label, (x + 16, y + 4), FONT, 0.33, TEXT_RGB, 1, cv2.LINE_AA)
        return x + 22 + cv2.getTextSize(label, FONT, 0.33, 1)[0][0] + 8

    if truth:
        x = entry(x, "truth (dot: front)", lambda x: cv2.rectangle(img, (x, y - 4), (x + 12, y + 4), TRUE_RGB, 2))
    x = entry(x, "ego", lambda x: cv2.rectangle(img, (x, y - 4), (x + 12, y + 4), EGO_RGB, -1))
    x = entry(x, "wheel contact", lambda x: cv2.circle(img, (x + 6, y), 2, WHEEL_RGB, -1, cv2.LINE_AA))
    x = entry(x, "front (voted)", lambda x: cv2.arrowedLine(img, (x, y), (x + 12, y), TEXT_RGB, 1, cv2.LINE_AA,
                                                             tipLength=0.4))
    entry(x, "axis only", lambda x: cv2.line(img, (x, y), (x + 12, y), TEXT_RGB, 1, cv2.LINE_AA))
    x, y = 6, top + 30
    cv2.putText(img, "estimates by camera:", (x, y + 4), FONT, 0.33, TEXT_RGB, 1, cv2.LINE_AA)
    x += cv2.getTextSize("estimates by camera:", FONT, 0.33, 1)[0][0] + 8
    for name in camera_names:
        x = entry(x, name, lambda x, n=name: cv2.rectangle(img, (x, y - 4), (x + 12, y + 4), camera_colour(n), 1))
    x, y = 6, top + 46
    entry(x, "paler: lower confidence (under a more confident footprint, or a poor fit)",
          lambda x: cv2.rectangle(img, (x, y - 4), (x + 12, y + 4), faded(TEXT_RGB, 0.0), 1))


def panel_grid(panels: list[np.ndarray], columns: int = 4) -> np.ndarray:
    """Equal-sized RGB panels in rows of ``columns``, the last row padded with white: a frame's truth and six
    method panels side by side made an image seven panels wide, too wide to read at any zoom."""
    h, w, c = panels[0].shape
    rows = [list(panels[i:i + columns]) for i in range(0, len(panels), columns)]
    if len(rows) > 1:
        rows[-1] += [np.full((h, w, c), 255, panels[0].dtype)] * (columns - len(rows[-1]))
    return np.concatenate([np.concatenate(row, axis=1) for row in rows], axis=0)
