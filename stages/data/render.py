"""Per-pixel ray casting of a Scene into the four fisheye cameras.

Each camera's per-pixel ray directions are computed once (``CameraTables``); a frame then intersects them
analytically with the ground plane (a texture holding markings and shadows, looked up with cv2.remap),
the vehicles' oriented boxes (lower body and cabin) and wheel cylinders, and the props' boxes. Rays that
hit nothing see the sky and the skyline. The per-pixel object-id buffer and each object's unoccluded
pixel count are what the labels are made from. Geometry lives in ``raycast``, colours in ``shading``,
sky and ground in ``backdrop``, camera effects in ``sensor``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import cv2
import numpy as np

from stages.data.backdrop import (
    SKYLINE_BINS,
    SKYLINE_R,
    TEX_HALF,
    TEX_RES,
    Look,
    sky_colours,
    skyline_colours,
)
from stages.data.bodies import Vehicle, make_vehicle
from stages.data.camera import FisheyeCamera
from stages.data.props import Prop
from stages.data.raycast import (
    box_regions,
    clip_crop,
    face_axis,
    intersect_box,
    intersect_wheel,
    local_rays,
    mask_bbox,
    or_into,
    zwrite,
)
from stages.data.sensor import corner_falloff
from stages.data.shading import Light, body_colour, prop_colour, wheel_colour
from stages.data.world import Scene

EGO_ID = -2
PROP_ID = -3
NO_ID = -1
EGO_SUN = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])  # the ego's own body is lit the same in every frame


@dataclass
class CameraTables:
    """What a camera needs per pixel, computed once per process."""

    cam: FisheyeCamera
    rays: np.ndarray          # (H, W, 3) float32 unit directions, ego frame
    valid: np.ndarray         # (H, W) bool: inside the lens' field of view
    ground_map: tuple         # cv2.remap maps (float32) into the ground texture
    fog: tuple                # cv2.blendLinear weights (ground, haze), float32 (H, W) each
    outside_idx: np.ndarray   # flat indices of pixels outside the lens' field of view (black)
    sky_idx: np.ndarray       # flat indices of sky pixels
    sky_elev: np.ndarray      # sine of each sky ray's elevation
    sky_az: np.ndarray        # azimuth (whole degrees, 0..359) of each sky ray
    sky_sector: np.ndarray    # skyline sector of each sky ray
    sky_sector_frac: np.ndarray  # position within the sector, 0..1
    sky_height: np.ndarray    # height at which each sky ray crosses the backdrop radius
    falloff: np.ndarray       # (H, W) vignetting shape
    ego_t: np.ndarray         # (H, W) float32 depth of the ego's own body (inf elsewhere)
    ego_rgb: np.ndarray       # (H, W, 3) uint8 the ego's body where ego_t is finite
    ego_mask: np.ndarray | None = None  # (H, W) uint8 where the ego's body is
    base_ids: np.ndarray | None = None  # (H, W) int16 id buffer before any vehicle: ego or nothing


def build_tables(cam: FisheyeCamera, ego: Vehicle) -> CameraTables:
    rays, valid = cam.pixel_rays()
    h, w = valid.shape
    oz = cam.position[2]
    dz = rays[..., 2]
    ground = valid & (dz < -1e-4)
    with np.errstate(divide="ignore"):
        t = np.where(ground, -oz / np.minimum(dz, -1e-4), 0.0)
    gx = cam.position[0] + t * rays[..., 0]
    gy = cam.position[1] + t * rays[..., 1]
    map_x = np.where(ground, (gx + TEX_HALF) / TEX_RES, -10).astype(np.float32)
    map_y = np.where(ground, (TEX_HALF - gy) / TEX_RES, -10).astype(np.float32)
    dist = np.where(ground, np.hypot(gx, gy), 0)
    fog = (1 - np.exp(-dist / 90.0)).astype(np.float32)
    sky = valid & ~ground
    idx = np.flatnonzero(sky)
    d = rays.reshape(-1, 3)[idx]
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360
    sector_width = 360 / SKYLINE_BINS
    horiz = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-6)
    height = oz + SKYLINE_R * d[:, 2] / horiz
    tables = CameraTables(cam=cam, rays=rays, valid=valid, ground_map=(map_x, map_y), fog=(1 - fog, fog),
                          outside_idx=np.flatnonzero(~valid), sky_idx=idx,
                          sky_elev=np.clip(d[:, 2], 0, 1).astype(np.float32), sky_az=az.astype(np.int32),
                          sky_sector=(az // sector_width).astype(np.int32) % SKYLINE_BINS,
                          sky_sector_frac=((az % sector_width) / sector_width).astype(np.float32),
                          sky_height=height.astype(np.float32), falloff=corner_falloff(w, h),
                          ego_t=np.full((h, w), np.inf, np.float32), ego_rgb=np.zeros((h, w, 3), np.uint8))
    # the ego's own body, seen at the image borders as on a real rig
    ids = np.full((h, w), NO_ID, np.int16)
    own = np.zeros(4, np.int64)
    render_vehicle(tables, ego, EGO_ID, None, tables.ego_t, ids, tables.ego_rgb, EGO_SUN, 1.0, own)
    tables.ego_mask = np.isfinite(tables.ego_t).astype(np.uint8)
    tables.base_ids = ids
    return tables


def ego_vehicle(cfg: dict) -> Vehicle:
    """The ego: a mid-size silver sedan, deterministic (the rig is the same in every frame)."""
    v = make_vehicle(np.random.default_rng(0), "sedan", 0.0, 0.0, 0.0)
    v.length, v.width, v.height = cfg["length"], cfg["width"], cfg["height"]
    v.colour = np.array([0.7, 0.71, 0.73])
    v.__post_init__()
    return v


# --- objects ------------------------------------------------------------------------------------------

def vehicle_boxes(v: Vehicle):
    """Bounding boxes (centre, rotation, half) of: the whole vehicle, each body part, each wheel."""
    R = v.rotation
    centres = [v.to_ego(np.array([0.0, 0.0, v.height / 2]))]
    halves = [v.bounds_half()]
    for _, c, h in v.parts():
        centres.append(c)
        halves.append(h)
    for k in range(4):
        centres.append(v.wheel_centre(k))
        halves.append(np.array([v.wheel_r, v.wheel_w / 2, v.wheel_r]))
    return np.array(centres), np.repeat(R[None], len(centres), axis=0), np.array(halves)


def render_vehicle(tables: CameraTables, v: Vehicle, vid: int, wheel_ids, tbuf, ids, rgb, sun, sun_strength,
                   own_counts, crops=None, own_boxes=None) -> np.ndarray | None:
    """Ray-cast one vehicle; returns its unoccluded mask over its crop (or None out of view), and fills
    own_counts[k] with each wheel's unoccluded pixel count and, when given, own_boxes[k] with its unoccluded
    bbox (None where it covers nothing)."""
    cam = tables.cam
    R = v.rotation
    if crops is None:
        crops = box_regions(cam, *vehicle_boxes(v))
    vc = crops[0]
    if vc[2] <= vc[0] or vc[3] <= vc[1]:
        return None
    own = np.zeros((vc[3] - vc[1], vc[2] - vc[0]), bool)
    light = Light(sun=(R.T @ sun).astype(np.float32), strength=float(sun_strength))
    parts = v.parts()
    for k, (name, centre, half) in enumerate(parts):
        crop = clip_crop(crops[1 + k], vc)
        if crop is None:
            continue
        dl, valid = local_rays(tables.rays, tables.valid, crop, R)
        o = R.T @ (cam.position - centre)
        t, near = intersect_box(o, dl, half)
        t[~valid] = np.inf

        hit = zwrite(crop, t, tbuf, ids, rgb, vid, partial(_shade_box_hits, dl=dl, o=o, t=t, near=near,
                                                             shade=partial(body_colour, v, name, half, light=light)))
        or_into(own, hit, crop, vc)
    hw = v.wheel_w / 2
    origin = R.T @ (cam.position - v.to_ego(np.zeros(3)))
    for k in range(4):
        crop = clip_crop(crops[1 + len(parts) + k], vc)
        if crop is None:
            continue
        dl, valid = local_rays(tables.rays, tables.valid, crop, R)
        _, _, (wx, wy) = v.wheels[k]
        o = origin - np.array([wx, wy, v.wheel_r])
        t, on_cap = intersect_wheel(o, dl, v.wheel_r, hw)
        t[~valid] = np.inf

        wid = vid if wheel_ids is None else wheel_ids[k]
        hit = zwrite(crop, t, tbuf, ids, rgb, wid, partial(_shade_wheel_hits, v=v, dl=dl, o=o, t=t, on_cap=on_cap,
                                                           light=light))
        own_counts[k] = int(hit.sum()) if wheel_ids is not None else 0
        if own_boxes is not None:
            own_boxes[k] = mask_bbox(hit, crop[0], crop[1])
        or_into(own, hit, crop, vc)
    return own


def render_props(tables: CameraTables, props: list[Prop], tbuf, ids, rgb, sun, sun_strength) -> None:
    """Ray-cast every prop box (id PROP_ID: they occlude, they are not labelled)."""
    boxes = [(p, b) for p in props for b in p.boxes]
    if not boxes:
        return
    cam = tables.cam
    rots = np.array([p.rotation for p, _ in boxes])
    crops = box_regions(cam, np.array([b.centre for _, b in boxes]), rots, np.array([b.half for _, b in boxes]))
    for (prop, box), R, crop in zip(boxes, rots, crops, strict=True):
        if crop[2] <= crop[0] or crop[3] <= crop[1]:
            continue
        dl, valid = local_rays(tables.rays, tables.valid, crop, R)
        o = R.T @ (cam.position - box.centre)
        t, near = intersect_box(o, dl, box.half)
        t[~valid] = np.inf
        light = Light(sun=(R.T @ sun).astype(np.float32), strength=float(sun_strength))
        shade = partial(_shade_prop, box.colour, prop.kind, light=light)
        zwrite(tuple(int(c) for c in crop), t, tbuf, ids, rgb, PROP_ID,
               partial(_shade_box_hits, dl=dl, o=o, t=t, near=near, shade=shade))


def _shade_box_hits(win, dl, o, t, near, shade):
    """Colours of the rays ``win`` that hit a box first: hit points, face axis and side, passed to
    ``shade(p, view, axis, sign)``."""
    axis = face_axis(near, win)
    dw = dl[:, win]
    sign = -np.sign(dw[axis, np.arange(len(axis))])
    return shade(o + t[win, None] * dw.T, dw.T, axis, sign)


def _shade_wheel_hits(win, v: Vehicle, dl, o, t, on_cap, light: Light):
    p = o + t[win, None] * dl[:, win].T
    return wheel_colour(v.wheel_look, v.wheel_r, p, on_cap[win], float(np.sign(o[1])), light)


def _shade_prop(colour, kind, p, view, axis, sign, light: Light):
    return prop_colour(colour, kind, p, axis, sign, light)


# --- frame --------------------------------------------------------------------------------------------

@dataclass
class ObjectStats:
    """Per rendered object: unoccluded pixels (in image and FOV), visible pixels, visible bbox, unoccluded bbox."""

    own_px: int
    visible_px: int
    bbox: tuple[int, int, int, int] | None  # x1, y1, x2, y2 (x2, y2 exclusive)
    own_bbox: tuple[int, int, int, int] | None = None  # where the object would be seen unoccluded


def render_background(tables: CameraTables, tex: np.ndarray, look: Look, clouds: np.ndarray) -> np.ndarray:
    """The ground (with haze towards the horizon), the sky and skyline, black outside the field of view,
    and the ego's own body: everything before the scene's objects."""
    ground = cv2.remap(tex, tables.ground_map[0], tables.ground_map[1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=tuple(int(c) for c in tex[0, 0]))
    haze = np.empty_like(ground)
    haze[:] = np.clip(look.horizon * 235, 0, 255).astype(np.uint8)
    rgb = cv2.blendLinear(ground, haze, *tables.fog)
    sky = sky_colours(look, tables.sky_elev, tables.sky_az, clouds)
    hit, facade = skyline_colours(look, tables.sky_height, tables.sky_sector, tables.sky_sector_frac)
    sky[hit] = facade
    flat = rgb.reshape(-1, 3)
    flat[tables.sky_idx] = (np.clip(sky, 0, 1) * 255).astype(np.uint8)
    flat[tables.outside_idx] = 0
    cv2.copyTo(tables.ego_rgb, tables.ego_mask, rgb)
    return rgb


def render_camera(tables: CameraTables, scene: Scene, tex: np.ndarray, look: Look, clouds: np.ndarray):
    """Render one camera: returns (rgb uint8 before sensor effects, id buffer, per-vehicle stats,
    per-wheel stats)."""
    cam = tables.cam
    rgb = render_background(tables, tex, look, clouds)
    tbuf = tables.ego_t.copy()
    ids = tables.base_ids.copy()
    nv = len(scene.vehicles)
    own_masks, wheel_own = [], np.zeros((nv, 4), np.int64)
    wheel_own_boxes = [[None] * 4 for _ in range(nv)]
    all_boxes = [vehicle_boxes(v) for v in scene.vehicles]
    per_vehicle = [len(b[0]) for b in all_boxes]
    crops = []
    if nv:
        flat = box_regions(cam, np.concatenate([b[0] for b in all_boxes]), np.concatenate([b[1] for b in all_boxes]),
                           np.concatenate([b[2] for b in all_boxes]))
        crops = np.split(flat, np.cumsum(per_vehicle)[:-1])
    for i, v in enumerate(scene.vehicles):
        wheel_ids = [nv + 4 * i + k for k in range(4)]
        own_masks.append(render_vehicle(tables, v, i, wheel_ids, tbuf, ids, rgb, look.sun, look.sun_strength,
                                        wheel_own[i], crops=crops[i], own_boxes=wheel_own_boxes[i]))
    render_props(tables, scene.props, tbuf, ids, rgb, look.sun, look.sun_strength)
    vehicles, wheels = [], []
    for i in range(nv):
        own = own_masks[i]
        if own is None:
            vehicles.append(ObjectStats(0, 0, None))
            wheels.extend(ObjectStats(0, 0, None) for _ in range(4))
            continue
        x0, y0, x1, y1 = crops[i][0]
        idc = ids[y0:y1, x0:x1]
        wid0 = nv + 4 * i
        vis = (idc == i) | ((idc >= wid0) & (idc < wid0 + 4))
        vehicles.append(ObjectStats(int(own.sum()), int(vis.sum()), mask_bbox(vis, x0, y0), mask_bbox(own, x0, y0)))
        for k in range(4):
            wv = idc == wid0 + k
            wheels.append(ObjectStats(int(wheel_own[i, k]), int(wv.sum()), mask_bbox(wv, x0, y0),
                                      wheel_own_boxes[i][k]))
    return rgb, ids, vehicles, wheels
