"""The randomisation space of the generator (``data.domain``): which families of each axis a dataset draws.

Each axis (body families, paints, materials, wheel styles, skies, grounds, prop kinds) lists the families
a dataset may draw, uniformly; the numeric ranges (sun, sensor, prop counts) are drawn within their bounds.
The in-domain dataset (``data=synword``) and the held-out one (``shift.data``) list disjoint families on
the axes the cross-domain benchmark holds out (docs/domain.md), so a model trained on the first meets the
second's families for the first time at test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.data.backdrop import GROUNDS, SKIES
from stages.data.bodies import BODY_FAMILIES, MATERIALS, PAINTS, WHEEL_STYLES
from stages.data.props import PROP_KINDS
from stages.data.sensor import SensorRanges, parse_range

AXES = {"bodies": tuple(BODY_FAMILIES), "paints": PAINTS, "materials": MATERIALS, "wheels": WHEEL_STYLES,
        "skies": SKIES, "grounds": GROUNDS, "props": PROP_KINDS}


@dataclass(frozen=True)
class DomainConfig:
    bodies: tuple[str, ...]
    paints: tuple[str, ...]
    materials: tuple[str, ...]
    wheels: tuple[str, ...]
    skies: tuple[str, ...]
    grounds: tuple[str, ...]
    props: tuple[str, ...]
    props_per_frame: tuple[int, int]
    props_near_vehicles: float
    sun_elevation_deg: tuple[float, float]
    sensor: SensorRanges

    @classmethod
    def from_cfg(cls, cfg: dict, where: str = "data.domain") -> DomainConfig:
        """Validate ``cfg`` (the plain ``data.domain`` dict); errors name the offending field."""
        if not isinstance(cfg, dict):
            raise ValueError(f"{where}: expected a mapping, got {cfg!r}")
        families = {}
        for axis, known in AXES.items():
            names = cfg.get(axis)
            if not isinstance(names, (list, tuple)) or (axis != "props" and not names):
                raise ValueError(f"{where}.{axis}: expected a non-empty list of families from {list(known)}, got {names!r}")
            unknown = [n for n in names if n not in known]
            if unknown:
                raise ValueError(f"{where}.{axis}: unknown families {unknown}; known: {list(known)}")
            families[axis] = tuple(dict.fromkeys(names))  # order kept, duplicates dropped
        lo, hi = parse_range(cfg, "props_per_frame", where, 0)
        near = float(cfg.get("props_near_vehicles", 0.5))
        if not 0 <= near <= 1:
            raise ValueError(f"{where}.props_near_vehicles: expected a share in [0, 1], got {near}")
        return cls(**families, props_per_frame=(int(lo), int(hi)), props_near_vehicles=near,
                   sun_elevation_deg=parse_range(cfg, "sun_elevation_deg", where, 1),
                   sensor=SensorRanges.from_cfg(cfg.get("sensor"), f"{where}.sensor"))

    def draw(self, rng: np.random.Generator, axis: str) -> str:
        names = getattr(self, axis)
        return names[int(rng.integers(len(names)))]
