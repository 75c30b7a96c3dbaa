"""Vehicles: body families, dimensions, wheel styles, paints and materials (the generator's vehicle side of
domain randomisation).

A vehicle is two boxes (the lower body and the cabin/greenhouse) and four wheel cylinders, which covers
two-box silhouettes (sedan, hatchback, SUV, pickup: a cabin shorter than the body) and one-box
silhouettes (van, bus: a cabin almost as long as the body). Each family draws its dimensions and where
its cabin sits; wheel styles, paints and materials are drawn independently of the family.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, field

import numpy as np

# Per family: (min, max) length, width, height, wheel radius (m); belt = height of the lower body's top;
# cabin = (length share, rear gap share): the cabin's length and how far its back stands from the tail,
# both as shares of the length; wheelbase as a share of the length.
BODY_FAMILIES = {
    "sedan": {"length": (4.3, 4.95), "width": (1.74, 1.88), "height": (1.38, 1.50), "wheel_r": (0.30, 0.34),
              "belt": (0.88, 0.98), "cabin": ((0.44, 0.52), (0.16, 0.22)), "wheelbase": (0.58, 0.62)},
    "hatchback": {"length": (3.6, 4.35), "width": (1.64, 1.80), "height": (1.42, 1.56), "wheel_r": (0.28, 0.32),
                  "belt": (0.88, 0.98), "cabin": ((0.58, 0.66), (0.03, 0.07)), "wheelbase": (0.60, 0.66)},
    "suv": {"length": (4.3, 5.0), "width": (1.82, 2.0), "height": (1.62, 1.85), "wheel_r": (0.34, 0.40),
            "belt": (1.0, 1.1), "cabin": ((0.6, 0.7), (0.03, 0.07)), "wheelbase": (0.58, 0.62)},
    "van": {"length": (4.8, 5.8), "width": (1.9, 2.05), "height": (1.9, 2.4), "wheel_r": (0.32, 0.36),
            "belt": (1.0, 1.1), "cabin": ((0.8, 0.86), (0.01, 0.03)), "wheelbase": (0.56, 0.62)},
    "pickup": {"length": (5.0, 5.8), "width": (1.85, 2.05), "height": (1.75, 1.95), "wheel_r": (0.36, 0.41),
               "belt": (1.05, 1.18), "cabin": ((0.3, 0.38), (0.4, 0.46)), "wheelbase": (0.58, 0.64)},
    "bus": {"length": (7.5, 10.0), "width": (2.3, 2.5), "height": (2.7, 3.2), "wheel_r": (0.44, 0.50),
            "belt": (1.15, 1.3), "cabin": ((0.95, 0.97), (0.01, 0.02)), "wheelbase": (0.52, 0.58)},
}
WHEEL_STYLES = ("alloy", "hubcap", "steel", "plain")
MATERIALS = ("matte", "glossy")
PAINTS = ("palette", "pastel", "vivid")

PALETTE = np.array([  # common car colours (RGB 0..1)
    [0.92, 0.92, 0.93], [0.08, 0.08, 0.09], [0.55, 0.56, 0.58], [0.75, 0.76, 0.78], [0.60, 0.08, 0.07],
    [0.10, 0.20, 0.50], [0.15, 0.30, 0.20], [0.80, 0.70, 0.50], [0.35, 0.22, 0.15], [0.85, 0.55, 0.10],
    [0.30, 0.45, 0.65], [0.95, 0.85, 0.20],
])
RIM_COLOURS = np.array([[0.65, 0.66, 0.68], [0.25, 0.25, 0.27], [0.80, 0.80, 0.78], [0.55, 0.48, 0.32]])


@dataclass
class WheelLook:
    """How a vehicle's wheels look: style, rim colour and radius share, spoke count, tyre grey."""

    style: str
    rim: np.ndarray
    rim_share: float      # rim radius / wheel radius
    spokes: int
    tyre: float


@dataclass
class Vehicle:
    """A vehicle standing on the ground. Local frame: x forward, y left, z up, origin on the ground below
    the body centre. Body = lower box + cabin (greenhouse) box; four wheels, outer faces flush with the body."""

    kind: str
    x: float
    y: float
    yaw: float
    length: float
    width: float
    height: float
    wheel_r: float
    wheelbase: float
    front_overhang: float
    colour: np.ndarray
    clearance: float
    belt: float           # height of the lower body's top (bonnet / window sill)
    cabin_len: float
    cabin_x: float        # cabin centre along x (local)
    wheel_w: float = 0.22
    paint: str = "palette"
    material: str = "matte"
    wheel_look: WheelLook | None = None
    wheels: list = field(default_factory=list)  # filled by __post_init__

    def __post_init__(self):
        xf = self.length / 2 - self.front_overhang
        xr = xf - self.wheelbase
        yw = self.width / 2 - self.wheel_w / 2 + 0.02  # slightly proud of the body: arches show the tyre
        # (axle, side, local centre): rear first on each side, the order wheel_pairs use
        self.wheels = [("rear", "left", (xr, yw)), ("front", "left", (xf, yw)),
                       ("rear", "right", (xr, -yw)), ("front", "right", (xf, -yw))]

    @property
    def rotation(self) -> np.ndarray:
        """Columns = local axes in the ego frame (local -> ego)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_ego(self, local: np.ndarray) -> np.ndarray:
        return np.asarray(local) @ self.rotation.T + np.array([self.x, self.y, 0.0])

    def parts(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """Body boxes as (name, centre in ego frame, half extents in the local frame)."""
        lower = np.array([0.0, 0.0, (self.clearance + self.belt) / 2])
        lower_h = np.array([self.length / 2, self.width / 2, (self.belt - self.clearance) / 2])
        cabin = np.array([self.cabin_x, 0.0, (self.belt + self.height) / 2])
        cabin_h = np.array([self.cabin_len / 2, self.width / 2 - 0.08, (self.height - self.belt) / 2])
        return [("lower", self.to_ego(lower), lower_h), ("cabin", self.to_ego(cabin), cabin_h)]

    def wheel_centre(self, i: int) -> np.ndarray:
        _, _, (x, y) = self.wheels[i]
        return self.to_ego(np.array([x, y, self.wheel_r]))

    def bounds_half(self) -> np.ndarray:
        """Half extents of a local box (centred at height/2) holding every part."""
        return np.array([self.length / 2, self.width / 2 + 0.03, self.height / 2])


def _span(rng: np.random.Generator, lo_hi, u: float | None = None) -> float:
    lo, hi = lo_hi
    return lo + (rng.random() if u is None else u) * (hi - lo)


def draw_paint(rng: np.random.Generator, paint: str) -> np.ndarray:
    """palette: common car colours; pastel: any hue, light and desaturated; vivid: any hue, saturated."""
    if paint == "palette":
        colour = PALETTE[rng.integers(len(PALETTE))] * rng.uniform(0.85, 1.1)
    elif paint == "pastel":
        colour = np.array(colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.1, 0.35), rng.uniform(0.7, 0.95)))
    elif paint == "vivid":
        colour = np.array(colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.75, 1.0), rng.uniform(0.45, 0.95)))
    else:
        raise ValueError(f"unknown paint family {paint!r}; known: {PAINTS}")
    return np.clip(colour, 0, 1)


def draw_wheel_look(rng: np.random.Generator, style: str) -> WheelLook:
    if style not in WHEEL_STYLES:
        raise ValueError(f"unknown wheel style {style!r}; known: {WHEEL_STYLES}")
    rim = RIM_COLOURS[rng.integers(len(RIM_COLOURS))] * rng.uniform(0.85, 1.1)
    if style == "steel":  # painted steel wheels: dark or body-grey
        rim = np.full(3, rng.uniform(0.12, 0.35))
    share = {"alloy": (0.55, 0.72), "hubcap": (0.6, 0.72), "steel": (0.5, 0.62), "plain": (0.2, 0.3)}[style]
    return WheelLook(style=style, rim=np.clip(rim, 0, 1), rim_share=float(rng.uniform(*share)),
                     spokes=int(rng.integers(4, 11)), tyre=float(rng.uniform(0.04, 0.12)))


def make_vehicle(rng: np.random.Generator, kind: str, x: float, y: float, yaw: float, paint: str = "palette",
                 material: str = "matte", wheel_style: str = "alloy") -> Vehicle:
    if kind not in BODY_FAMILIES:
        raise ValueError(f"unknown body family {kind!r}; known: {sorted(BODY_FAMILIES)}")
    spec = BODY_FAMILIES[kind]
    u = rng.random()  # one size factor: bigger vehicles are also wider, with longer wheelbases and wheels
    length = _span(rng, spec["length"], u)
    width = _span(rng, spec["width"], 0.6 * u + 0.4 * rng.random())
    height = _span(rng, spec["height"])
    wheel_r = _span(rng, spec["wheel_r"], 0.5 * u + 0.5 * rng.random())
    wheelbase = length * _span(rng, spec["wheelbase"])
    front_overhang = (length - wheelbase) * rng.uniform(0.45, 0.6)
    belt = min(_span(rng, spec["belt"]), height - 0.35)
    share, rear_gap = spec["cabin"]
    cabin_len = length * _span(rng, share)
    cabin_x = -length / 2 + length * _span(rng, rear_gap) + cabin_len / 2
    return Vehicle(kind=kind, x=x, y=y, yaw=yaw, length=length, width=width, height=height, wheel_r=wheel_r,
                   wheelbase=wheelbase, front_overhang=front_overhang, colour=draw_paint(rng, paint),
                   clearance=wheel_r * rng.uniform(0.55, 0.8), belt=belt, cabin_len=cabin_len, cabin_x=cabin_x,
                   wheel_w=0.18 + 0.08 * u + (0.08 if kind == "bus" else 0.0), paint=paint, material=material,
                   wheel_look=draw_wheel_look(rng, wheel_style))
