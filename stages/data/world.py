"""The 3D world of one frame: vehicles on a ground plane with markings, around the ego (ego frame: x forward,
y left, z up, metres). Scenes are the cases surround-view systems exist for: the ego parked between close
neighbours, dense perpendicular/angled/parallel parking on both sides of an aisle, and highway traffic
from free flow to jams in adjacent lanes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# (length, width, height, wheel radius) ranges per vehicle type; wheelbase and track follow the size.
VEHICLE_TYPES = {
    "car": {"length": (3.7, 4.8), "width": (1.65, 1.85), "height": (1.38, 1.52), "wheel_r": (0.29, 0.33)},
    "suv": {"length": (4.3, 5.0), "width": (1.82, 2.0), "height": (1.62, 1.82), "wheel_r": (0.34, 0.39)},
    "van": {"length": (4.8, 5.6), "width": (1.9, 2.05), "height": (1.9, 2.35), "wheel_r": (0.32, 0.36)},
}

PAINT = np.array([  # common car colours (RGB 0..1)
    [0.92, 0.92, 0.93], [0.08, 0.08, 0.09], [0.55, 0.56, 0.58], [0.75, 0.76, 0.78], [0.60, 0.08, 0.07],
    [0.10, 0.20, 0.50], [0.15, 0.30, 0.20], [0.80, 0.70, 0.50], [0.35, 0.22, 0.15], [0.85, 0.55, 0.10],
    [0.30, 0.45, 0.65], [0.95, 0.85, 0.20],
])


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


def make_vehicle(rng: np.random.Generator, kind: str, x: float, y: float, yaw: float) -> Vehicle:
    spec = VEHICLE_TYPES[kind]
    u = rng.random()  # one size factor: bigger cars are also wider, with longer wheelbases
    length = spec["length"][0] + u * (spec["length"][1] - spec["length"][0])
    width = spec["width"][0] + (0.6 * u + 0.4 * rng.random()) * (spec["width"][1] - spec["width"][0])
    height = spec["height"][0] + rng.random() * (spec["height"][1] - spec["height"][0])
    wheel_r = spec["wheel_r"][0] + (0.5 * u + 0.5 * rng.random()) * (spec["wheel_r"][1] - spec["wheel_r"][0])
    wheelbase = length * rng.uniform(0.58, 0.63)
    front_overhang = (length - wheelbase) * rng.uniform(0.5, 0.6)
    belt = {"car": 0.92, "suv": 1.05, "van": 1.05}[kind] + rng.uniform(-0.05, 0.05)
    if kind == "van":
        cabin_len, cabin_x = length * 0.82, -length * 0.07
    else:
        cabin_len = length * rng.uniform(0.46, 0.56)
        cabin_x = -length * rng.uniform(0.04, 0.1)
    colour = PAINT[rng.integers(len(PAINT))] * rng.uniform(0.85, 1.1)
    return Vehicle(kind=kind, x=x, y=y, yaw=yaw, length=length, width=width, height=height, wheel_r=wheel_r,
                   wheelbase=wheelbase, front_overhang=front_overhang, colour=np.clip(colour, 0, 1),
                   clearance=wheel_r * rng.uniform(0.55, 0.8), belt=belt, cabin_len=cabin_len, cabin_x=cabin_x,
                   wheel_w=0.18 + 0.08 * u)


@dataclass
class Marking:
    """A painted stripe on the ground: a segment (x0, y0) -> (x1, y1) of a width (m); dashed if dash > 0."""

    p0: tuple[float, float]
    p1: tuple[float, float]
    width: float = 0.12
    colour: tuple[float, float, float] = (0.85, 0.85, 0.82)
    dash: float = 0.0


@dataclass
class Scene:
    kind: str
    layout: str
    vehicles: list[Vehicle]
    markings: list[Marking]
    asphalt: np.ndarray


class SceneSampler:
    """Draws scenes from the configured mix. ``cfg`` is the ``data.scenes`` config (plain dict)."""

    def __init__(self, cfg: dict, ego_length: float, ego_width: float):
        self.cfg = cfg
        self.ego_half = (ego_length / 2, ego_width / 2)
        self.types = list(cfg["vehicle_types"])
        self.type_p = _normalised(cfg["vehicle_types"])

    def sample(self, rng: np.random.Generator) -> Scene:
        kind = _choice(rng, self.cfg["mix"])
        layout = _choice(rng, self.cfg[kind]["layouts"])
        vehicles, markings = getattr(self, f"_{kind}_{layout}")(rng)
        vehicles = _without_overlaps([v for v in vehicles if math.hypot(v.x, v.y) < self.cfg["max_range"]
                                      and self._clear_of_ego(v)])
        asphalt = np.array([0.34, 0.34, 0.35]) * rng.uniform(0.75, 1.2) + rng.uniform(-0.03, 0.03, 3)
        return Scene(kind=kind, layout=layout, vehicles=vehicles, markings=markings, asphalt=np.clip(asphalt, 0, 1))

    def _vehicle(self, rng, x, y, yaw) -> Vehicle:
        kind = self.types[rng.choice(len(self.types), p=self.type_p)]
        return make_vehicle(rng, kind, x, y, yaw)

    def _clear_of_ego(self, v: Vehicle) -> bool:
        """Reject a vehicle whose footprint (inflated by 0.25 m) would touch the ego (separating axis test)."""
        a = _footprint(0.0, 0.0, 0.0, self.ego_half[0] + 0.25, self.ego_half[1] + 0.25)
        b = _footprint(v.x, v.y, v.yaw, v.length / 2, v.width / 2)
        return _separated(a, b)

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
        fp = _footprint(v.x, v.y, v.yaw, v.length / 2 + 0.05, v.width / 2 + 0.05)
        near = [p for k, p in zip(kept, prints, strict=True) if math.hypot(k.x - v.x, k.y - v.y) < 6.0]
        if all(_separated(fp, p) for p in near):
            kept.append(v)
            prints.append(fp)
    return kept


def _footprint(x, y, yaw, hx, hy) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    corners = np.array([[hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]])
    return corners @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def _separated(a: np.ndarray, b: np.ndarray) -> bool:
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return True
    return False
