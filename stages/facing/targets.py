"""What the facing network learns which way a vehicle faces from (``facing.targets``, docs/bev.md "Front and back").

- **3D truth** (``deepword.facing.box_facings``): a record with ``calibration`` and ``objects_3d`` gives every vehicle
  its image direction from rear to front, where both ground points lie in view.
- **The roles of a labelled couple** (``role_facings``): a record without 3D truth, a team's images labelled in 2D,
  gives a vehicle whose couple is labelled rear and front (``wheel_pairs``, the roles in its relations) the image
  direction from the rear wheel box's bottom centre to the front one's. On the generator's records, which have both,
  it points the way the 3D truth does for every such vehicle: 1,542 of 1,542 train vehicles in domain (median 1.8 deg
  apart, 90th percentile 12.7) and 3,869 of 3,869 of the held-out domain's pool (2.0 / 14.8 deg); 43 % of the vehicles
  with a 3D target have such a couple (the rest are seen end-on, or one wheel shows).

A record keeps to one source: its 3D truth where it has it, so a dataset with 3D truth trains as before. ``roles_only``
names data sources (a record's ``data_source``, stages/data/compose.py) whose 3D truth is left out: the adaptation
experiment's pool playing a team's camera that was labelled in 2D only (docs/adapt.md)."""

from __future__ import annotations

import numpy as np

from deepword.facing import box_facings
from deepword.format_3d import has_3d_truth

SOURCE_KEY = "data_source"   # stages.data.compose.SOURCE_KEY (not imported: the facing stage does not need data's)
MIN_SPAN_PX = 1.0            # wheels whose bottoms lie closer than this (pixels) give no direction


def role_facings(record) -> np.ndarray:
    """(N, 2) per box of ``record``: for a vehicle with a labelled couple of a rear and a front wheel, the unit image
    vector from the rear wheel box's bottom centre to the front one's; NaN for every other box (the first such couple
    of a vehicle counts)."""
    out = np.full((len(record.boxes), 2), np.nan, dtype=np.float32)
    row = {int(b): i for i, b in enumerate(record.box_ids)}
    roles: dict[int, dict[str, list[int]]] = {}
    for vehicle, wheel, role in record.relations:
        if role is not None:
            roles.setdefault(int(vehicle), {}).setdefault(role, []).append(int(wheel))
    couples = {frozenset((int(a), int(b))) for a, b in record.wheel_pairs}
    for vehicle, by_role in roles.items():
        if vehicle not in row:
            continue
        for rear in by_role.get("rear", []):
            front = next((f for f in by_role.get("front", []) if frozenset((rear, f)) in couples), None)
            if front is None or rear not in row or front not in row:
                continue
            a, b = record.boxes[row[rear]], record.boxes[row[front]]
            d = np.array([(b[0] + b[2] - a[0] - a[2]) / 2, b[3] - a[3]], dtype=np.float64)
            span = float(np.hypot(d[0], d[1]))
            if span >= MIN_SPAN_PX:
                out[row[vehicle]] = d / span
                break
    return out


def target_source(record, objects_3d: bool = True, roles: bool = True,
                  roles_only: tuple[str, ...] | list[str] = ()) -> str | None:
    """Where ``facing_targets`` takes the record's targets from: ``objects_3d`` (its 3D truth, where it has it, the
    setting allows it and its ``data_source`` is not in ``roles_only``), else ``roles`` (where allowed), else None."""
    if objects_3d and has_3d_truth(record) and record.extra.get(SOURCE_KEY) not in set(roles_only):
        return "objects_3d"
    return "roles" if roles else None


def facing_targets(record, objects_3d: bool = True, roles: bool = True,
                   roles_only: tuple[str, ...] | list[str] = ()) -> np.ndarray:
    """(N, 2) per box: the record's facing targets (NaN: none) from ``target_source``."""
    source = target_source(record, objects_3d, roles, roles_only)
    if source == "objects_3d":
        return box_facings(record)
    if source == "roles":
        return role_facings(record)
    return np.full((len(record.boxes), 2), np.nan, dtype=np.float32)


def count_targets(records, **settings) -> dict[str, int]:
    """{source: vehicles with a target from it} over ``records`` (``settings``: ``facing_targets``' keywords)."""
    counts = {"objects_3d": 0, "roles": 0}
    for rec in records:
        source = target_source(rec, **settings)
        if source is not None:
            counts[source] += int(np.isfinite(facing_targets(rec, **settings)).all(axis=1).sum())
    return counts


def target_settings(fcfg) -> dict:
    """``facing_targets``' keywords from the ``facing`` config's ``targets`` (absent, older configs: 3D truth, then
    roles, no source roles only); refuses settings that leave nothing to learn from."""
    tcfg = fcfg.get("targets") or {}
    settings = {"objects_3d": bool(tcfg.get("objects_3d", True)), "roles": bool(tcfg.get("roles", True)),
                "roles_only": tuple(str(s) for s in (tcfg.get("roles_only") or ()))}
    if not (settings["objects_3d"] or settings["roles"]):
        raise ValueError("facing.targets: objects_3d and roles are both false: the facing network has nothing to "
                         "learn from (set one true, or leave the stage out: pipeline.skip=[facing])")
    return settings
