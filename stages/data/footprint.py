"""Ground footprints (oriented rectangles on z = 0) and the separating-axis test scene sampling uses to keep
vehicles and props from overlapping each other and the ego."""

from __future__ import annotations

import math

import numpy as np


def footprint(x: float, y: float, yaw: float, hx: float, hy: float) -> np.ndarray:
    """The four corners (4, 2) of a rectangle of half sizes hx (along yaw) and hy centred at (x, y)."""
    c, s = math.cos(yaw), math.sin(yaw)
    corners = np.array([[hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]])
    return corners @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def separated(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two convex quadrilaterals do not touch (an edge normal of either separates them)."""
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return True
    return False
