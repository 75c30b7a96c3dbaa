"""Colours of the surfaces rays hit: vehicle bodies (paint, material, windows, lights, bumpers), wheels
(tyre and rim styles) and props. Each function shades only the rays that won the depth test, from the
hit points in the part's local frame, the face or normal hit and the sun (in the same local frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.data.bodies import Vehicle, WheelLook

SHININESS = 24.0


@dataclass(frozen=True)
class Light:
    """The sun in a part's local frame and how strong its direct light is (1 clear, ~0 overcast)."""

    sun: np.ndarray
    strength: float

    def shade(self, lam: np.ndarray) -> np.ndarray:
        """Brightness of a surface whose normal makes cos = ``lam`` with the sun: ambient + direct."""
        ambient = 0.45 + 0.25 * (1 - self.strength)
        return ambient + 0.6 * self.strength * np.maximum(lam, 0)


def _to_uint8(col: np.ndarray) -> np.ndarray:
    return np.clip(col * 255, 0, 255).astype(np.uint8)


def body_colour(v: Vehicle, part: str, half: np.ndarray, p: np.ndarray, view: np.ndarray, axis: np.ndarray,
                sign: np.ndarray, light: Light) -> np.ndarray:
    """(n, 3) uint8 colour of hits ``p`` (part frame) on a body box entered through face ``axis`` on side
    ``sign``; ``view`` (n, 3) the ray directions."""
    n = len(axis)
    normal = np.zeros((n, 3), np.float32)
    normal[np.arange(n), axis] = sign
    lam = normal @ light.sun
    col = np.broadcast_to(v.colour.astype(np.float32), (n, 3)).copy()
    _paint_details(col, p, axis, sign, half, part)
    col = col * light.shade(lam)[:, None]
    if v.material == "glossy":  # Blinn-Phong highlight and a sky sheen on upward faces
        to_eye = -view / np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-9)
        h = to_eye + light.sun
        h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-9)
        spec = np.maximum((normal * h).sum(1), 0) ** SHININESS * 0.7 * light.strength
        col = col + spec[:, None] + 0.08 * (normal[:, 2:3] > 0)
    return _to_uint8(col)


def _paint_details(col, p, axis, sign, half, part: str) -> None:
    """Windows on the cabin, lights and bumper on the lower body (p: hit points in the part's frame)."""
    z_rel = p[:, 2] + half[2]  # height above the part's bottom
    if part == "cabin":
        side = (axis == 1) & (np.abs(p[:, 0]) < half[0] - 0.12) & (np.abs(p[:, 0]) > 0.04)
        ends = (axis == 0) & (np.abs(p[:, 1]) < half[1] - 0.1)
        glass = (side | ends) & (z_rel > 0.05) & (z_rel < 2 * half[2] - 0.06)
        col[glass] = np.array([0.1, 0.12, 0.16]) + 0.18 * (z_rel[glass, None] / (2 * half[2]))
        return
    top = 2 * half[2]
    lights = (axis == 0) & (z_rel > top - 0.2) & (z_rel < top - 0.06) & (np.abs(p[:, 1]) > half[1] - 0.42) \
        & (np.abs(p[:, 1]) < half[1] - 0.08)
    front = sign > 0
    col[lights & front] = (0.95, 0.93, 0.85)
    col[lights & ~front] = (0.75, 0.05, 0.04)
    bumper = (z_rel < 0.14) | ((axis == 0) & (z_rel < 0.3) & front & (np.abs(p[:, 1]) < 0.5))
    col[bumper] = col[bumper] * 0.35


def wheel_colour(look: WheelLook, radius: float, p: np.ndarray, on_cap: np.ndarray, outward: float,
                 light: Light) -> np.ndarray:
    """(n, 3) uint8 colour of hits ``p`` (wheel frame: axle along y) on the tread or on the outer face (cap)."""
    rad = np.hypot(p[:, 0], p[:, 2]) / radius
    n_side = np.stack([p[:, 0], np.zeros_like(rad), p[:, 2]], 1) / radius
    n_cap = np.zeros_like(n_side)
    n_cap[:, 1] = outward
    normal = np.where(on_cap[:, None], n_cap, n_side)
    col = np.full((len(rad), 3), look.tyre, np.float32)
    rim = on_cap & (rad < look.rim_share)
    col[rim] = look.rim
    angle = np.arctan2(p[:, 2], p[:, 0])
    if look.style == "alloy":  # spokes between dark gaps, a dark hub
        gaps = rim & (rad > 0.2) & (rad < look.rim_share - 0.06) & (np.abs(np.sin(look.spokes / 2 * angle)) > 0.7)
        col[gaps] = col[gaps] * 0.35
        col[on_cap & (rad < 0.14)] = look.rim * 0.5
    elif look.style == "hubcap":  # a plastic disc with a raised ring and vents
        col[rim & (np.abs(rad - 0.45) < 0.04)] = look.rim * 0.7
        vents = rim & (rad > 0.25) & (rad < 0.4) & (np.abs(np.sin(look.spokes * angle)) > 0.85)
        col[vents] = col[vents] * 0.3
    elif look.style == "steel":  # a painted disc with a ring of holes and wheel nuts
        holes = rim & (np.abs(rad - 0.35) < 0.06) & (np.abs(np.sin(look.spokes / 2 * angle)) > 0.85)
        col[holes] = look.tyre
        col[on_cap & (rad < 0.12)] = look.rim * 1.3
    # "plain": a bare tyre with a small hub (rim_share is small)
    return _to_uint8(col * light.shade(normal @ light.sun)[:, None])


def prop_colour(base: np.ndarray, kind: str, p: np.ndarray, axis: np.ndarray, sign: np.ndarray,
                light: Light) -> np.ndarray:
    """(n, 3) uint8 colour of a prop box: Lambert shading, a leafy mottle on tree crowns and a storey
    pattern (windows) on buildings."""
    n = len(axis)
    normal = np.zeros((n, 3), np.float32)
    normal[np.arange(n), axis] = sign
    col = np.broadcast_to(base.astype(np.float32), (n, 3)).copy()
    if kind == "tree":
        mottle = np.sin(p[:, 0] * 7.1) * np.sin(p[:, 1] * 6.3 + p[:, 2] * 5.7)
        col *= (0.8 + 0.3 * mottle)[:, None]
    elif kind == "building":
        along = np.where(axis == 0, p[:, 1], p[:, 0])
        windows = (axis != 2) & ((p[:, 2] % 3.0) > 1.0) & ((p[:, 2] % 3.0) < 2.2) & ((along % 2.0) > 0.8)
        col[windows] = col[windows] * 0.35 + np.array([0.1, 0.13, 0.18])
    return _to_uint8(col * light.shade(normal @ light.sun)[:, None])
