"""Props: everything in the world that is neither a vehicle nor the ground, built from boxes (walls,
buildings, trees, poles, bollards, kerbs, pedestrian-like figures, traffic cones and random crates near
the vehicles). They occlude vehicles and wheels like any surface but are never annotated, so the labels
stay those of the vehicles; they cast shadows on the ground like the vehicles do.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import numpy as np

from stages.data.footprint import footprint, separated

PROP_KINDS = ("wall", "building", "tree", "pole", "bollard", "kerb", "pedestrian", "cone", "crate")
NEAR_VEHICLE_KINDS = ("pedestrian", "cone", "crate", "bollard")  # the clutter that stands right beside cars


@dataclass
class PropBox:
    """One box of a prop: centre (ego frame, m), half extents (local), colour (RGB 0..1)."""

    centre: np.ndarray
    half: np.ndarray
    colour: np.ndarray


@dataclass
class Prop:
    kind: str
    x: float
    y: float
    yaw: float
    boxes: list[PropBox]

    @property
    def rotation(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def height(self) -> float:
        return max(float(b.centre[2] + b.half[2]) for b in self.boxes)

    def ground_half(self) -> tuple[float, float]:
        """Half sizes of the footprint along and across yaw (the widest box)."""
        return max(float(b.half[0]) for b in self.boxes), max(float(b.half[1]) for b in self.boxes)


def _grey(rng, lo, hi) -> np.ndarray:
    return np.full(3, rng.uniform(lo, hi)) * rng.uniform(0.95, 1.05, 3)


def _hue(rng, sat, val) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(rng.random(), rng.uniform(*sat), rng.uniform(*val)))


def _box(x, y, z_bottom, half_xy, height, colour) -> PropBox:
    return PropBox(np.array([x, y, z_bottom + height / 2]), np.array([half_xy[0], half_xy[1], height / 2]),
                   np.clip(np.asarray(colour, float), 0, 1))


def make_prop(rng: np.random.Generator, kind: str, x: float, y: float, yaw: float) -> Prop:
    """A prop of ``kind`` standing at (x, y); its boxes share the prop's yaw."""
    c, s = math.cos(yaw), math.sin(yaw)

    def at(dx, dy):  # a point of the prop's local frame in the ego frame
        return x + c * dx - s * dy, y + s * dx + c * dy

    boxes: list[PropBox]
    if kind == "wall":
        boxes = [_box(x, y, 0, (rng.uniform(3, 12), rng.uniform(0.1, 0.25)), rng.uniform(0.8, 2.6),
                      _grey(rng, 0.35, 0.8) if rng.random() < 0.6 else _hue(rng, (0.2, 0.6), (0.35, 0.75)))]
    elif kind == "building":
        colour = _grey(rng, 0.4, 0.85) if rng.random() < 0.5 else _hue(rng, (0.15, 0.55), (0.35, 0.85))
        boxes = [_box(x, y, 0, (rng.uniform(4, 12), rng.uniform(3, 8)), rng.uniform(4, 14), colour)]
    elif kind == "tree":
        trunk_h = rng.uniform(1.5, 3.0)
        crown = rng.uniform(1.0, 2.5)
        boxes = [_box(x, y, 0, (0.15, 0.15), trunk_h, (0.3, 0.22, 0.15)),
                 _box(x, y, trunk_h, (crown, crown), rng.uniform(1.5, 3.5),
                      np.array([0.15, 0.4, 0.12]) * rng.uniform(0.6, 1.4))]
    elif kind == "pole":
        h = rng.uniform(3, 8)
        colour = _grey(rng, 0.25, 0.65)
        boxes = [_box(x, y, 0, (0.07, 0.07), h, colour)]
        if rng.random() < 0.5:  # a lamp arm
            ax, ay = at(0.6, 0.0)
            boxes.append(_box(ax, ay, h - 0.12, (0.6, 0.06), 0.1, colour))
    elif kind == "bollard":
        boxes = [_box(x, y, 0, (0.08, 0.08), rng.uniform(0.6, 1.1),
                      (0.9, 0.75, 0.1) if rng.random() < 0.4 else _grey(rng, 0.2, 0.7))]
    elif kind == "kerb":
        boxes = [_box(x, y, 0, (rng.uniform(4, 15), 0.12), rng.uniform(0.1, 0.2), _grey(rng, 0.55, 0.8))]
    elif kind == "pedestrian":
        h = rng.uniform(1.5, 1.9)
        clothes = _hue(rng, (0.1, 0.8), (0.15, 0.8))
        lx, ly = at(0.0, 0.08)
        rx, ry = at(0.0, -0.08)
        legs = _hue(rng, (0.0, 0.5), (0.1, 0.5))
        skin = np.array([0.85, 0.65, 0.5]) * rng.uniform(0.5, 1.1)
        boxes = [_box(lx, ly, 0, (0.08, 0.07), 0.47 * h, legs), _box(rx, ry, 0, (0.08, 0.07), 0.47 * h, legs),
                 _box(x, y, 0.47 * h, (0.12, 0.21), 0.4 * h, clothes), _box(x, y, 0.87 * h, (0.1, 0.09), 0.13 * h, skin)]
    elif kind == "cone":
        boxes = [_box(x, y, 0, (0.2, 0.2), 0.05, (0.1, 0.1, 0.1)), _box(x, y, 0.05, (0.1, 0.1), 0.6, (0.95, 0.4, 0.05))]
    elif kind == "crate":
        side = rng.uniform(0.25, 0.7)
        boxes = [_box(x, y, 0, (side * rng.uniform(0.7, 1.5), side), side * rng.uniform(0.6, 2.0),
                      _hue(rng, (0.0, 1.0), (0.2, 0.95)))]
    else:
        raise ValueError(f"unknown prop kind {kind!r}; known: {PROP_KINDS}")
    return Prop(kind=kind, x=x, y=y, yaw=yaw, boxes=boxes)


def place_props(rng: np.random.Generator, kinds: tuple[str, ...], count: int, near_share: float, vehicles: list,
                keep_out: list[np.ndarray], max_range: float) -> list[Prop]:
    """Up to ``count`` props of the given kinds, none touching a vehicle, the ego (``keep_out`` footprints)
    or another prop. A share ``near_share`` of the small kinds stands beside a random vehicle (0.3-1.5 m
    from its side or end), the rest anywhere within ``max_range``; large kinds stand further out."""
    placed: list[Prop] = []
    blocked = list(keep_out) + [footprint(v.x, v.y, v.yaw, v.length / 2 + 0.15, v.width / 2 + 0.15) for v in vehicles]
    for _ in range(count):
        kind = kinds[rng.integers(len(kinds))]
        yaw = rng.uniform(-math.pi, math.pi)
        if kind in NEAR_VEHICLE_KINDS and vehicles and rng.random() < near_share:
            v = vehicles[rng.integers(len(vehicles))]
            side = rng.choice([-1.0, 1.0])
            if rng.random() < 0.7:  # beside a flank
                local = (rng.uniform(-v.length / 2, v.length / 2), side * (v.width / 2 + rng.uniform(0.3, 1.5)))
            else:  # beyond the nose or the tail
                local = (side * (v.length / 2 + rng.uniform(0.3, 1.5)), rng.uniform(-v.width / 2, v.width / 2))
            c, s = math.cos(v.yaw), math.sin(v.yaw)
            x, y = v.x + c * local[0] - s * local[1], v.y + s * local[0] + c * local[1]
        else:
            near, far = (12.0, max_range) if kind in ("building", "wall") else (3.0, max_range * 0.8)
            r, a = rng.uniform(near, far), rng.uniform(-math.pi, math.pi)
            x, y = r * math.cos(a), r * math.sin(a)
            if kind in ("wall", "kerb", "building"):  # long props run along the x or y axis, like the lots
                yaw = rng.choice([0.0, math.pi / 2]) + rng.normal(0, 0.05)
        prop = make_prop(rng, kind, x, y, yaw)
        hx, hy = prop.ground_half()
        fp = footprint(x, y, yaw, hx + 0.05, hy + 0.05)
        if all(separated(fp, b) for b in blocked):
            placed.append(prop)
            blocked.append(fp)
    return placed
