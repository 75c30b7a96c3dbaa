"""The 3D world of one frame: vehicles on a ground plane with markings, around the ego (ego frame: x forward,
y left, z up, metres). Scenes are the cases surround-view systems exist for: the ego parked between close
neighbours, dense perpendicular/angled/parallel parking on both sides of an aisle, and highway traffic
from free flow to jams in adjacent lanes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stages.data.bodies import Vehicle, make_vehicle
from stages.data.domain import DomainConfig
from stages.data.footprint import footprint, separated
from stages.data.props import Prop, place_props


@dataclass
class Marking:
    """A painted stripe on the ground: a segment (x0, y0) -> (x1, y1) of a width (m); dashed if dash > 0;
    colour None: the frame's marking paint (white or yellow, drawn per frame)."""

    p0: tuple[float, float]
    p1: tuple[float, float]
    width: float = 0.12
    colour: tuple[float, float, float] | None = None
    dash: float = 0.0


@dataclass
class Scene:
    kind: str
    layout: str
    vehicles: list[Vehicle]
    markings: list[Marking]
    props: list[Prop]


class SceneSampler:
    """Draws scenes from the configured mix. ``cfg`` is the ``data.scenes`` config (plain dict); ``domain``
    says which body families, paints, materials, wheel styles and props the scene may hold."""

    def __init__(self, cfg: dict, domain: DomainConfig, ego_length: float, ego_width: float):
        self.cfg = cfg
        self.domain = domain
        self.ego_half = (ego_length / 2, ego_width / 2)

    def sample(self, rng: np.random.Generator) -> Scene:
        kind = _choice(rng, self.cfg["mix"])
        layout = _choice(rng, self.cfg[kind]["layouts"])
        vehicles, markings = getattr(self, f"_{kind}_{layout}")(rng)
        vehicles = _without_overlaps([v for v in vehicles if math.hypot(v.x, v.y) < self.cfg["max_range"]
                                      and self._clear_of_ego(v)])
        d = self.domain
        n_props = int(rng.integers(d.props_per_frame[0], d.props_per_frame[1] + 1)) if d.props else 0
        props = place_props(rng, d.props, n_props, d.props_near_vehicles, vehicles, [self._ego_footprint(0.3)],
                            self.cfg["max_range"])
        return Scene(kind=kind, layout=layout, vehicles=vehicles, markings=markings, props=props)

    def _vehicle(self, rng, x, y, yaw) -> Vehicle:
        d = self.domain
        return make_vehicle(rng, d.draw(rng, "bodies"), x, y, yaw, paint=d.draw(rng, "paints"),
                            material=d.draw(rng, "materials"), wheel_style=d.draw(rng, "wheels"))

    def _ego_footprint(self, grow: float) -> np.ndarray:
        return footprint(0.0, 0.0, 0.0, self.ego_half[0] + grow, self.ego_half[1] + grow)

    def _clear_of_ego(self, v: Vehicle) -> bool:
        """Reject a vehicle whose footprint would touch the ego inflated by 0.25 m (separating axis test)."""
        return separated(self._ego_footprint(0.25), footprint(v.x, v.y, v.yaw, v.length / 2, v.width / 2))

    # --- parking ----------------------------------------------------------------------------------
    def _row(self, rng, origin, along, facing, n_slots, pitch, angle, occupancy, skip=()) -> list[Vehicle]:
        """A row of slots: slot k's centre is origin + k * pitch * along; cars point ``facing`` rotated by
        (90 - angle) deg towards ``along`` for angled bays, nose-in or reversed at random."""
        out = []
        tilt = math.radians(90 - angle)
        base_yaw = math.atan2(facing[1], facing[0])
        along_yaw = math.atan2(along[1], along[0])
        # tilt the heading from the row normal towards the row direction
        sgn = math.copysign(1.0, math.sin(along_yaw - base_yaw))
        for k in range(-n_slots, n_slots + 1):
            if k in skip or rng.random() > occupancy:
                continue
            cx = origin[0] + k * pitch * along[0]
            cy = origin[1] + k * pitch * along[1]
            yaw = base_yaw + sgn * tilt
            if angle >= 80 and rng.random() < 0.45:  # perpendicular bays: many reverse in
                yaw += math.pi
            yaw += rng.normal(0, math.radians(3))
            v = self._vehicle(rng, 0, 0, yaw)
            inset = rng.uniform(-0.35, 0.35)  # how deep the car sits in its bay
            lat = rng.normal(0, 0.12)
            hx, hy = math.cos(yaw), math.sin(yaw)
            v.x = cx + inset * hx - lat * hy
            v.y = cy + inset * hy + lat * hx
            out.append(v)
        return out

    def _bay_lines(self, origin, along, facing, n_slots, pitch, depth, angle) -> list[Marking]:
        lines = []
        tilt = math.radians(90 - angle)
        c, s = math.cos(tilt), math.sin(tilt)
        # line direction: the facing vector tilted towards ``along``
        d = (facing[0] * c + along[0] * s, facing[1] * c + along[1] * s)
        for k in range(-n_slots, n_slots + 2):
            bx = origin[0] + (k - 0.5) * pitch * along[0]
            by = origin[1] + (k - 0.5) * pitch * along[1]
            half = depth / 2 / max(c, 0.3)
            lines.append(Marking((bx - d[0] * half, by - d[1] * half), (bx + d[0] * half, by + d[1] * half)))
        return lines

    def _slot_geometry(self, rng):
        pc = self.cfg["parking"]
        angle = 90.0 if rng.random() < pc["perpendicular_share"] else float(rng.uniform(45, 65))
        width = rng.uniform(*pc["slot_width"])
        pitch = width / math.sin(math.radians(angle))
        depth = rng.uniform(4.8, 5.3)
        return angle, pitch, depth

    def _parking_ego_in_slot(self, rng):
        """The ego parked in a bay between close neighbours; the aisle and the opposite row ahead or behind;
        a back-to-back row behind the ego's row."""
        pc = self.cfg["parking"]
        pitch = rng.uniform(*pc["slot_width"])  # the ego's own row is perpendicular
        depth = rng.uniform(4.8, 5.3)
        aisle = rng.uniform(*pc["aisle_width"])
        side = 1.0 if rng.random() < 0.5 else -1.0  # aisle in front (+x) or behind (-x) of the ego
        occ = rng.uniform(*pc["occupancy"])
        n = 6
        along = (0.0, 1.0)
        vehicles = self._row(rng, (0.0, 0.0), along, (side, 0.0), n, pitch, 90.0, occ, skip={0, -1, 1})
        for k in (-1, 1):  # close neighbours are (almost) always there
            if rng.random() < pc["neighbour_prob"]:
                vehicles += self._row(rng, (0.0, k * pitch), along, (side, 0.0), 0, pitch, 90.0, 1.0)
        opp_x = side * (depth + aisle)
        opp_angle = 90.0 if rng.random() < 0.6 else float(rng.uniform(45, 65))
        opp_pitch = pitch / math.sin(math.radians(opp_angle))
        vehicles += self._row(rng, (opp_x, rng.uniform(-1, 1)), along, (-side, 0.0), n, opp_pitch, opp_angle, occ)
        back_x = -side * depth
        vehicles += self._row(rng, (back_x, rng.uniform(-1, 1)), along, (-side, 0.0), n, pitch, 90.0, occ * 0.9)
        if rng.random() < 0.5:  # a car moving along the aisle
            vehicles.append(self._vehicle(rng, side * (depth / 2 + aisle / 2), rng.uniform(-8, 8),
                                          math.pi / 2 * rng.choice([-1, 1]) + rng.normal(0, 0.05)))
        marks = self._bay_lines((0.0, 0.0), along, (side, 0.0), n, pitch, depth, 90.0)
        marks += self._bay_lines((opp_x, 0.0), along, (-side, 0.0), n, opp_pitch, depth, opp_angle)
        marks += self._bay_lines((back_x, 0.0), along, (-side, 0.0), n, pitch, depth, 90.0)
        return vehicles, marks

    def _parking_aisle(self, rng):
        """The ego driving (or waiting) in the aisle between two dense rows, back-to-back rows beyond."""
        pc = self.cfg["parking"]
        angle, pitch, depth = self._slot_geometry(rng)
        aisle = rng.uniform(*pc["aisle_width"])
        occ = rng.uniform(*pc["occupancy"])
        off = rng.uniform(-0.8, 0.8)  # the ego is not always centred in the aisle
        n = 7
        vehicles, marks = [], []
        for side in (1.0, -1.0):
            row_y = side * (aisle / 2 + depth / 2) + off
            shift = rng.uniform(0, pitch)
            vehicles += self._row(rng, (shift, row_y), (1.0, 0.0), (0.0, -side), n, pitch, angle, occ)
            marks += self._bay_lines((shift, row_y), (1.0, 0.0), (0.0, -side), n, pitch, depth, angle)
            back_y = row_y + side * depth
            vehicles += self._row(rng, (shift + rng.uniform(0, pitch), back_y), (1.0, 0.0), (0.0, side), n,
                                  pitch, angle, occ * 0.85)
        if rng.random() < 0.5:  # queueing car ahead / behind in the aisle
            gap = rng.uniform(1.0, 3.0)
            v = self._vehicle(rng, 0, off + rng.normal(0, 0.2), rng.normal(0, 0.04))
            v.x = rng.choice([1, -1]) * (self.ego_half[0] + gap + v.length / 2)
            vehicles.append(v)
        return vehicles, marks

    def _parking_parallel(self, rng):
        """The ego parallel-parked at the kerb with cars close ahead and behind; a street with parked cars
        on the far side and traffic in between."""
        pc = self.cfg["parking"]
        side = 1.0 if rng.random() < 0.5 else -1.0  # kerb on the ego's left or right
        street = rng.uniform(6.0, 9.0)
        vehicles, marks = [], []

        def parallel_row(y0, yaw0, include_ego_gap):
            x = self.ego_half[0] + rng.uniform(*pc["parallel_gap"]) if include_ego_gap else rng.uniform(-25, -18)
            row = []
            for direction in ((1.0, -1.0) if include_ego_gap else (1.0,)):
                cursor = x if direction > 0 else -x
                while abs(cursor) < 28:
                    v = self._vehicle(rng, 0, 0, yaw0 + rng.normal(0, 0.03))
                    cx = cursor + direction * v.length / 2
                    v.x, v.y = cx, y0 + rng.normal(0, 0.1)
                    if rng.random() < pc["occupancy"][1]:
                        row.append(v)
                    cursor = cx + direction * (v.length / 2 + rng.uniform(*pc["parallel_gap"]))
            return row

        vehicles += parallel_row(0.0, 0.0, True)
        far_y = side * -(street + 1.0)
        vehicles += parallel_row(far_y, math.pi if rng.random() < 0.5 else 0.0, False)
        if rng.random() < 0.6:  # passing traffic between the rows
            lane_y = -side * street / 2
            vehicles.append(self._vehicle(rng, rng.uniform(-6, 6), lane_y, rng.choice([0.0, math.pi])))
        kerb = side * 1.15
        marks.append(Marking((-30, kerb), (30, kerb), 0.15, (0.75, 0.75, 0.72)))
        marks.append(Marking((-30, -side * (street / 2 + 1.0)), (30, -side * (street / 2 + 1.0)), 0.12,
                             (0.85, 0.85, 0.8), dash=3.0))
        for k in range(-6, 7):
            marks.append(Marking((k * 6.0 - 2.9, 0.0), (k * 6.0 - 2.9, kerb), 0.1))
        return vehicles, marks

    # --- highway ----------------------------------------------------------------------------------
    def _highway_traffic(self, rng, gap_range, lane_fill):
        hc = self.cfg["highway"]
        n_lanes = int(rng.integers(hc["lanes"][0], hc["lanes"][1] + 1))
        lane_w = rng.uniform(3.3, 3.75)
        ego_lane = int(rng.integers(n_lanes))
        vehicles, marks = [], []
        for lane in range(n_lanes):
            y = (ego_lane - lane) * lane_w  # lanes to the right have negative y
            if rng.random() > lane_fill:
                continue
            cursor = rng.uniform(-45, -30)
            while cursor < 40:
                v = self._vehicle(rng, 0, 0, rng.normal(0, 0.025))
                v.x = cursor + v.length / 2
                v.y = y + rng.normal(0, 0.25)
                vehicles.append(v)
                cursor += v.length + rng.uniform(*gap_range)
        for b in range(n_lanes + 1):
            y = (ego_lane - b + 0.5) * lane_w
            edge = b in (0, n_lanes)
            marks.append(Marking((-60, y), (60, y), 0.2 if edge else 0.15, (0.9, 0.9, 0.85) if edge else
                                 (0.88, 0.88, 0.84), dash=0.0 if edge else 4.0))
        if rng.random() < 0.5:  # oncoming carriageway beyond the left edge
            y0 = (ego_lane + 0.5) * lane_w + rng.uniform(1.5, 3.0)
            for lane in range(2):
                y = y0 + (lane + 0.5) * lane_w
                cursor = rng.uniform(-45, -30)
                while cursor < 40:
                    v = self._vehicle(rng, 0, 0, math.pi + rng.normal(0, 0.02))
                    v.x, v.y = cursor + v.length / 2, y + rng.normal(0, 0.2)
                    vehicles.append(v)
                    cursor += v.length + rng.uniform(gap_range[0] * 2, gap_range[1] * 3)
        return vehicles, marks

    def _highway_jam(self, rng):
        return self._highway_traffic(rng, self.cfg["highway"]["jam_gap"], 1.0)

    def _highway_dense(self, rng):
        return self._highway_traffic(rng, self.cfg["highway"]["dense_gap"], 0.9)

    def _highway_free(self, rng):
        return self._highway_traffic(rng, self.cfg["highway"]["free_gap"], 0.6)


def _normalised(weights: dict) -> np.ndarray:
    p = np.array([float(w) for w in weights.values()])
    return p / p.sum()


def _choice(rng: np.random.Generator, weights: dict) -> str:
    keys = list(weights)
    return keys[rng.choice(len(keys), p=_normalised(weights))]


def _without_overlaps(vehicles: list[Vehicle]) -> list[Vehicle]:
    """Drop any vehicle whose footprint touches one already kept (jittered bays can collide)."""
    kept, prints = [], []
    for v in vehicles:
        fp = footprint(v.x, v.y, v.yaw, v.length / 2 + 0.05, v.width / 2 + 0.05)
        near = [p for k, p in zip(kept, prints, strict=True) if math.hypot(k.x - v.x, k.y - v.y) < (k.length + v.length) / 2 + 1.0]
        if all(separated(fp, p) for p in near):
            kept.append(v)
            prints.append(fp)
    return kept
