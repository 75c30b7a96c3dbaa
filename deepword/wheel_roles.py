"""Which of a vehicle's wheels is a front one and which a rear one, read from which way the vehicle faces.

The relation network's role head barely learns the roles (its val role accuracy stays near chance: a wheel's role is
an exclusive-or of which way its vehicle faces and which end the wheel sits at, and its crops keep too little of the
first). The footprints learn the first elsewhere (the facing network, the heading prior, the other cameras;
``deepword.footprint.heading_vote``), so once a vehicle's front is known its wheels' roles follow from where they
stand (docs/bev.md, "Front and back"):

- **from the footprint** (``footprint_roles``, with a calibration): a wheel whose ground contact lies ahead of its
  fused footprint's centre, along its heading, is a front wheel, else a rear one;
- **from the facing vector** (``facing_roles``, images without a calibration): a wheel ahead of its vehicle's other
  wheels along the vehicle box's facing vector (the image direction of its front) is a front wheel; a vehicle whose
  wheels lie close together in the image (one axle, or too far to tell) or that shows one wheel compares with the
  box's centre instead.

Roles written this way repeat the heading they were read from, so a record carrying them says so (``ROLES_FROM_KEY``)
and the footprints do not count them as a second vote (``network_roles``).
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import replace

import numpy as np

from deepword.facing import record_facing

ROLES_FROM_KEY = "roles_from"   # a record's extra key: {rule: relations whose role it wrote}; absent: the network's
FOOTPRINT, FACING, NETWORK = "footprint", "facing", "network"
# two wheels of one vehicle this share of its box's width apart (or more) in the image are told apart along the facing
# vector; closer ones (an axle seen end-on, a distant vehicle) compare with the box centre
APART_SHARE = 0.25

Roles = dict[tuple[int, int], str]   # (vehicle box_id, wheel box_id) -> "front" / "rear"


def network_roles(rec) -> dict[int, str]:
    """{wheel box_id: role} as the relation method wrote them, for the footprints' role votes; empty where the roles
    were read from the vehicle's front (``with_roles``): they would count that heading twice."""
    if ROLES_FROM_KEY in rec.extra:
        return {}
    return {w: r for _, w, r in rec.relations if r}


def footprint_roles(rec, groups, contacts: dict[int, np.ndarray]) -> Roles:
    """Each owned wheel's role from its vehicle's fused footprint: ``front`` where the wheel's ground contact lies
    ahead of the footprint's centre along its heading. ``groups``: the frame's fused footprints [(Box3D, estimates)];
    ``contacts``: {wheel box_id: (x, y)} of the wheels whose contact is known. Relations whose vehicle has no
    footprint from this image, or whose wheel has no contact, get none."""
    placed = {e.vehicle_box_id: box for box, g in groups for e in g
              if e.image == rec.image and e.vehicle_box_id is not None}
    out: Roles = {}
    for v, w, _ in rec.relations:
        box, xy = placed.get(v), contacts.get(w)
        if box is None or xy is None:
            continue
        ahead = (xy[0] - box.x) * math.cos(box.yaw) + (xy[1] - box.y) * math.sin(box.yaw)
        out[(v, w)] = "front" if ahead > 0 else "rear"
    return out


def facing_roles(rec) -> Roles:
    """Each owned wheel's role from its vehicle box's facing vector (``deepword.facing``; none for a vehicle without
    one): along the vector, ahead of the mean of the vehicle's wheel centres where they lie ``APART_SHARE`` of the box's
    width apart or more, else ahead of the box's centre."""
    vectors = record_facing(rec)
    rows = {int(b): i for i, b in enumerate(rec.box_ids)}
    xyxy = rec.xyxy
    centre = {b: np.array([(xyxy[i, 0] + xyxy[i, 2]) / 2, (xyxy[i, 1] + xyxy[i, 3]) / 2]) for b, i in rows.items()}
    owned = defaultdict(list)
    for v, w, _ in rec.relations:
        if v in vectors and v in rows and w in rows:
            owned[v].append(w)
    out: Roles = {}
    for v, wheels in owned.items():
        points = np.array([centre[w] for w in wheels])
        box_width = float(xyxy[rows[v], 2] - xyxy[rows[v], 0])
        apart = len(wheels) > 1 and float(np.ptp(points[:, 0])) >= APART_SHARE * box_width
        reference = points.mean(axis=0) if apart else centre[v]
        direction = np.asarray(vectors[v], dtype=np.float64)
        for w, p in zip(wheels, points, strict=True):
            out[(v, w)] = "front" if float(np.dot(p - reference, direction)) > 0 else "rear"
    return out


def with_roles(rec, by_rule: list[tuple[str, Roles]]):
    """``rec`` with each relation's role from the first rule of ``by_rule`` [(rule name, roles)] that gives one, else
    as the relation method wrote it; couples listed rear first where their roles differ; and ``ROLES_FROM_KEY``: how
    many relations each rule decided (``NETWORK``: left as written)."""
    counts = {name: 0 for name, _ in by_rule} | {NETWORK: 0}
    relations, role_of = [], {}
    for v, w, role in rec.relations:
        name, new = next(((name, roles[(v, w)]) for name, roles in by_rule if (v, w) in roles), (NETWORK, role))
        counts[name] += 1
        relations.append((v, w, new))
        role_of[w] = new
    pairs = [(b, a) if (role_of.get(a), role_of.get(b)) == ("front", "rear") else (a, b) for a, b in rec.wheel_pairs]
    return replace(rec, relations=relations, wheel_pairs=pairs, extra={**rec.extra, ROLES_FROM_KEY: counts})


def front_rules(rec, groups=(), contacts: dict[int, np.ndarray] | None = None) -> list[tuple[str, Roles]]:
    """The rules ``deepword infer`` reads roles by, in the order they decide (``with_roles``): the footprint where the
    vehicle has one from this image and the wheel a ground contact (``footprint_roles``; ``groups`` and ``contacts``
    as it takes them, none for an image without a camera), then the facing vector (``facing_roles``)."""
    return [(FOOTPRINT, footprint_roles(rec, groups, contacts or {})), (FACING, facing_roles(rec))]


def roles_from_front(rec, groups=(), contacts: dict[int, np.ndarray] | None = None):
    """``rec`` with its roles as ``deepword infer`` writes them: ``front_rules``, else the relation method's."""
    return with_roles(rec, front_rules(rec, groups, contacts))
