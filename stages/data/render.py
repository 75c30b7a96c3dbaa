"""Per-pixel ray casting of a Scene into the four fisheye cameras.

Each camera's per-pixel ray directions are computed once (``CameraTables``); a frame then intersects them
analytically with the ground plane (a texture holding markings and shadows, looked up with cv2.remap),
the vehicles' oriented boxes (lower body and cabin) and wheel cylinders. Each primitive is only tested
on the pixels of its projected bounding region (projected edge samples, so the curved fisheye images of
straight edges stay inside), which keeps a frame fast. The depth test gives correct occlusion; the
per-pixel object-id buffer and each object's unoccluded pixel count are what the labels are made from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from stages.data.camera import FisheyeCamera
from stages.data.world import Scene, Vehicle, make_vehicle

EGO_ID = -2
NO_ID = -1
TEX_RES = 0.05     # ground texture: metres per texel
TEX_HALF = 32.0    # the texture covers +-32 m around the ego
SKYLINE_R = 70.0   # distance of the backdrop (buildings, trees) around the scene
MARGIN_PX = 3
NOISE_PAD = 64

# the 12 edges of the unit cube [-1, 1]^3, 11 samples each: a box's image lies inside their images' bbox
_t = np.linspace(-1.0, 1.0, 11)
_EDGES = []
for _a in range(3):
    for _s1 in (-1.0, 1.0):
        for _s2 in (-1.0, 1.0):
            _p = np.zeros((11, 3))
            _p[:, _a] = _t
            _b, _c = [i for i in range(3) if i != _a]
            _p[:, _b], _p[:, _c] = _s1, _s2
            _EDGES.append(_p)
CUBE_EDGE_SAMPLES = np.concatenate(_EDGES)


@dataclass
class CameraTables:
    """What a camera needs per pixel, computed once per process."""

    cam: FisheyeCamera
    rays: np.ndarray          # (H, W, 3) float32 unit directions, ego frame
    valid: np.ndarray         # (H, W) bool: inside the lens' field of view
    ground_map: tuple         # cv2.remap maps (float32) into the ground texture
    fog: tuple                # cv2.blendLinear weights (ground, haze), float32 (H, W) each
    haze: np.ndarray          # (H, W, 3) uint8 haze colour
    outside_idx: np.ndarray   # flat indices of pixels outside the lens' field of view (black)
    sky_idx: np.ndarray       # flat indices of sky pixels
    sky_bin: np.ndarray       # azimuth bin (5 deg) of each sky pixel
    sky_height: np.ndarray    # height at which each sky ray crosses the backdrop radius
    sky_rgb: np.ndarray       # (n_sky, 3) float32 sky gradient
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
    horiz = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-6)
    height = oz + SKYLINE_R * d[:, 2] / horiz
    elev = np.clip(d[:, 2], 0, 1)[:, None]
    sky_rgb = ((1 - elev) * np.array([0.78, 0.82, 0.86]) + elev * np.array([0.45, 0.62, 0.85])).astype(np.float32)
    haze = np.broadcast_to(np.array([184, 191, 199], np.uint8), (h, w, 3)).copy()
    tables = CameraTables(cam=cam, rays=rays, valid=valid, ground_map=(map_x, map_y), fog=(1 - fog, fog),
                          haze=haze, outside_idx=np.flatnonzero(~valid), sky_idx=idx, sky_bin=(az // 5).astype(np.int32),
                          sky_height=height.astype(np.float32), sky_rgb=sky_rgb,
                          ego_t=np.full((h, w), np.inf, np.float32), ego_rgb=np.zeros((h, w, 3), np.uint8))
    # the ego's own body, seen at the image borders as on a real rig
    ids = np.full((h, w), NO_ID, np.int16)
    own = np.zeros(4, np.int64)
    sun = np.array([0.3, 0.2, 0.93])
    _render_vehicle(tables, ego, EGO_ID, None, tables.ego_t, ids, tables.ego_rgb, sun / np.linalg.norm(sun), own)
    tables.ego_mask = np.isfinite(tables.ego_t).astype(np.uint8)
    tables.base_ids = ids
    return tables


def ego_vehicle(cfg: dict) -> Vehicle:
    """The ego: a mid-size silver car, deterministic (the rig is the same in every frame)."""
    v = make_vehicle(np.random.default_rng(0), "car", 0.0, 0.0, 0.0)
    v.length, v.width, v.height = cfg["length"], cfg["width"], cfg["height"]
    v.colour = np.array([0.7, 0.71, 0.73])
    v.__post_init__()
    return v


# --- regions ------------------------------------------------------------------------------------------

def box_regions(cam: FisheyeCamera, centres: np.ndarray, rots: np.ndarray, halves: np.ndarray) -> np.ndarray:
    """Pixel crops (x0, y0, x1, y1) bounding the images of oriented boxes; x1 <= x0 when not in view.
    centres (B, 3), rots (B, 3, 3) local->ego, halves (B, 3)."""
    b = len(centres)
    if b == 0:
        return np.zeros((0, 4), np.int64)
    local = CUBE_EDGE_SAMPLES[None] * halves[:, None, :]                 # (B, S, 3)
    pts = local @ rots.transpose(0, 2, 1) + centres[:, None, :]
    uv = cam.project_cam(cam.to_cam(pts.reshape(-1, 3))).reshape(b, -1, 2)
    lo, hi = uv.min(axis=1) - MARGIN_PX, uv.max(axis=1) + MARGIN_PX
    crops = np.stack([np.floor(lo[:, 0]), np.floor(lo[:, 1]), np.ceil(hi[:, 0]) + 1, np.ceil(hi[:, 1]) + 1], 1)
    crops = np.clip(crops, 0, [cam.width, cam.height, cam.width, cam.height]).astype(np.int64)
    # the projection is continuous except straight behind the lens: a box containing the camera or the
    # ray straight back has an image the edge samples do not bound, so it gets the whole image
    o = ((cam.position[None] - centres)[:, None, :] @ rots)[:, 0]         # camera in each box's frame
    d = -cam.forward @ rots
    t_near, t_far = _slab(o, d, halves)
    inside = np.all(np.abs(o) <= halves, axis=1)
    behind = inside | ((t_near <= t_far) & (t_far > 0))
    crops[behind] = [0, 0, cam.width, cam.height]
    return crops


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    return np.minimum(t1, t2).max(axis=-1), np.maximum(t1, t2).min(axis=-1)


# --- primitives ---------------------------------------------------------------------------------------

def _intersect_box(o, d, half):
    """Rays o + t d (local frame; d as 3 component rows (3, N)) against a box centred at the origin:
    t (inf = miss) and the per-axis entry distances (to tell which face was hit)."""
    near = []
    t_far = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            inv = 1.0 / d[a]
            t1 = (-half[a] - o[a]) * inv
            t2 = (half[a] - o[a]) * inv
            near.append(np.minimum(t1, t2))
            far = np.maximum(t1, t2)
            t_far = far if t_far is None else np.minimum(t_far, far)
    tn = np.maximum(np.maximum(near[0], near[1]), near[2])
    hit = (tn <= t_far) & (tn > 1e-3)
    return np.where(hit, tn, np.inf).astype(np.float32), near


def _face_axis(near, win):
    nx, ny, nz = near[0][win], near[1][win], near[2][win]
    return np.where(nx >= ny, np.where(nx >= nz, 0, 2), np.where(ny >= nz, 1, 2))


def _intersect_wheel(o, d, r, hw):
    """Rays against a cylinder along local y (radius r, half width hw), centred at the origin: t, on_cap."""
    a = d[0] * d[0] + d[2] * d[2]
    b = 2 * (o[0] * d[0] + o[2] * d[2])
    c = o[0] ** 2 + o[2] ** 2 - r * r
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t_side = (-b - np.sqrt(disc)) / (2 * a)
        y_side = o[1] + t_side * d[1]
        side_ok = (disc >= 0) & (t_side > 1e-3) & (np.abs(y_side) <= hw)
        cap_y = hw if o[1] > 0 else -hw
        t_cap = (cap_y - o[1]) / d[1]
        xc = o[0] + t_cap * d[0]
        zc = o[2] + t_cap * d[2]
        cap_ok = (t_cap > 1e-3) & (xc * xc + zc * zc <= r * r) & (abs(o[1]) > hw)
    t_s = np.where(side_ok, t_side, np.inf)
    t_c = np.where(cap_ok, t_cap, np.inf)
    on_cap = t_c < t_s
    return np.minimum(t_s, t_c).astype(np.float32), on_cap


def _local_rays(tables: CameraTables, crop, R: np.ndarray):
    """The crop's ray directions in a local frame (rows x, y, z: (3, N)) and its in-FOV mask (N,)."""
    x0, y0, x1, y1 = crop
    d = tables.rays[y0:y1, x0:x1].reshape(-1, 3)
    return R.T.astype(np.float32) @ d.T, tables.valid[y0:y1, x0:x1].ravel()


def _zwrite(crop, t, tbuf, ids, rgb, oid, colour_fn):
    """Depth-test ``t`` (flat, over ``crop``) and write id and colour where it wins; returns the hit mask."""
    x0, y0, x1, y1 = crop
    shape = (y1 - y0, x1 - x0)
    tb = tbuf[y0:y1, x0:x1]
    t2 = t.reshape(shape)
    win = t2 < tb
    if win.any():
        tb[win] = t2[win]
        ids[y0:y1, x0:x1][win] = oid
        rgb[y0:y1, x0:x1][win] = colour_fn(win.ravel())
    return np.isfinite(t2)


def _render_vehicle(tables, v: Vehicle, vid: int, wheel_ids, tbuf, ids, rgb, sun, own_counts,
                    crops=None) -> np.ndarray | None:
    """Ray-cast one vehicle; returns its unoccluded mask over its crop (or None out of view), and fills
    own_counts[k] with each wheel's unoccluded pixel count."""
    cam = tables.cam
    R = v.rotation
    if crops is None:
        centres, rots, halves = _vehicle_boxes(v)
        crops = box_regions(cam, centres, rots, halves)
    vc = crops[0]
    if vc[2] <= vc[0] or vc[3] <= vc[1]:
        return None
    own = np.zeros((vc[3] - vc[1], vc[2] - vc[0]), bool)
    sun_l = R.T @ sun
    base = v.colour.astype(np.float32)
    for k, (name, centre, half) in enumerate(v.parts()):
        crop = _clip(crops[1 + k], vc)
        if crop is None:
            continue
        dl, valid = _local_rays(tables, crop, R)
        o = R.T @ (cam.position - centre)
        t, near = _intersect_box(o, dl, half)
        t[~valid] = np.inf

        def colour(win, dl=dl, o=o, t=t, near=near, half=half, name=name):
            axis = _face_axis(near, win)
            dw = dl[:, win]
            sign = -np.sign(dw[axis, np.arange(len(axis))])
            lam = np.maximum(sign * sun_l[axis], 0)
            shade = (0.45 + 0.6 * lam)[:, None]
            col = np.broadcast_to(base, (len(axis), 3)).copy()
            p = o + t[win, None] * dw.T
            _paint_details(col, p, axis, sign, half, v, name)
            return np.clip(col * shade * 255, 0, 255).astype(np.uint8)

        hit = _zwrite(crop, t, tbuf, ids, rgb, vid, colour)
        _or_into(own, hit, crop, vc)
    for k in range(4):
        crop = _clip(crops[3 + k], vc)
        if crop is None:
            continue
        dl, valid = _local_rays(tables, crop, R)
        _, _, (wx, wy) = v.wheels[k]
        o = R.T @ (cam.position - v.to_ego(np.array([0.0, 0.0, 0.0]))) - np.array([wx, wy, v.wheel_r])
        hw = v.wheel_w / 2
        t, on_cap = _intersect_wheel(o, dl, v.wheel_r, hw)
        t[~valid] = np.inf

        def wheel_colour(win, dl=dl, o=o, t=t, on_cap=on_cap):
            p = o + t[win, None] * dl[:, win].T
            rad = np.hypot(p[:, 0], p[:, 2]) / v.wheel_r
            cap = on_cap[win]
            n_side = np.stack([p[:, 0], np.zeros_like(rad), p[:, 2]], 1) / v.wheel_r
            n_cap = np.zeros_like(n_side)
            n_cap[:, 1] = np.sign(o[1])
            n = np.where(cap[:, None], n_cap, n_side)
            lam = np.maximum(n @ sun_l, 0)
            col = np.full((len(rad), 3), 0.07, np.float32)
            rim = cap & (rad < 0.62)
            col[rim] = 0.62
            col[cap & (rad < 0.14)] = 0.3
            spokes = rim & (rad > 0.2) & (np.abs(np.sin(5 * np.arctan2(p[:, 2], p[:, 0]))) > 0.75)
            col[spokes] = 0.25
            return np.clip(col * (0.5 + 0.6 * lam)[:, None] * 255, 0, 255).astype(np.uint8)

        wid = vid if wheel_ids is None else wheel_ids[k]
        hit = _zwrite(crop, t, tbuf, ids, rgb, wid, wheel_colour)
        own_counts[k] = int(hit.sum()) if wheel_ids is not None else 0
        _or_into(own, hit, crop, vc)
    return own


def _paint_details(col, p, axis, sign, half, v: Vehicle, name: str) -> None:
    """Windows on the cabin, lights and bumper on the lower body (p: hit points in the part's frame)."""
    z_rel = p[:, 2] + half[2]  # height above the part's bottom
    if name == "cabin":
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


def _vehicle_boxes(v: Vehicle):
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
    return np.array(centres), np.repeat(R[None], 7, axis=0), np.array(halves)


def _clip(crop, outer):
    x0, y0 = max(crop[0], outer[0]), max(crop[1], outer[1])
    x1, y1 = min(crop[2], outer[2]), min(crop[3], outer[3])
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _or_into(own, hit, crop, outer):
    x0, y0, x1, y1 = crop
    own[y0 - outer[1]:y1 - outer[1], x0 - outer[0]:x1 - outer[0]] |= hit


# --- frame --------------------------------------------------------------------------------------------

@dataclass
class ObjectStats:
    """Per rendered object: unoccluded pixels (in image and FOV), visible pixels, visible bbox."""

    own_px: int
    visible_px: int
    bbox: tuple[int, int, int, int] | None  # x1, y1, x2, y2 (x2, y2 exclusive)


def ground_texture(scene: Scene, noise: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """The frame's ground as a top-down RGB texture: asphalt, markings, soft shadows under vehicles."""
    light = 0.45 + 0.6 * max(sun[2], 0)
    gain = tuple(float(c * light * 2) for c in scene.asphalt) + (0.0,)  # noise is centred on 128
    tex = cv2.multiply(cv2.cvtColor(noise, cv2.COLOR_GRAY2RGB), gain)

    def px(x, y):  # metres -> texel, fixed point with 4 fractional bits (cv2 ``shift=4``)
        return int(round((x + TEX_HALF) / TEX_RES * 16)), int(round((TEX_HALF - y) / TEX_RES * 16))

    for m in scene.markings:
        colour = tuple(float(c * light * 255) for c in m.colour)
        thick = max(1, int(round(m.width / TEX_RES)))
        p0, p1 = np.array(m.p0, float), np.array(m.p1, float)
        length = np.linalg.norm(p1 - p0)
        if m.dash > 0:
            step = (p1 - p0) / length
            segs = [(p0 + step * s, p0 + step * min(s + m.dash, length)) for s in np.arange(0, length, 2.5 * m.dash)]
        else:
            segs = [(p0, p1)]
        for a, b in segs:
            cv2.line(tex, px(*a), px(*b), colour, thick, cv2.LINE_AA, shift=4)
    shade = np.full(noise.shape, 255, np.uint8)
    for v in scene.vehicles:
        for grow, val in ((0.25, 205), (0.05, 145)):  # penumbra, then the dark core under the body
            c, s = math.cos(v.yaw), math.sin(v.yaw)
            hx, hy = v.length / 2 + grow, v.width / 2 + grow
            corners = np.array([[hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]]) @ np.array([[c, s], [-s, c]])
            pts = np.array([px(v.x + x, v.y + y) for x, y in corners], np.int32)
            cv2.fillConvexPoly(shade, pts, val, cv2.LINE_AA, shift=4)
    return cv2.multiply(tex, cv2.cvtColor(shade, cv2.COLOR_GRAY2RGB), scale=1 / 255)


def render_camera(tables: CameraTables, scene: Scene, tex: np.ndarray, skyline: np.ndarray,
                  skyline_rgb: np.ndarray, sun: np.ndarray):
    """Render one camera: returns (rgb uint8 before noise, id buffer, per-vehicle stats, per-wheel stats)."""
    cam = tables.cam
    ground = cv2.remap(tex, tables.ground_map[0], tables.ground_map[1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=tuple(int(c) for c in tex[0, 0]))
    rgb = cv2.blendLinear(ground, tables.haze, *tables.fog)
    sky = tables.sky_rgb.copy()
    bld = tables.sky_height < skyline[tables.sky_bin]
    sky[bld] = skyline_rgb[tables.sky_bin[bld]]
    flat = rgb.reshape(-1, 3)
    flat[tables.sky_idx] = (sky * 255).astype(np.uint8)
    flat[tables.outside_idx] = 0
    cv2.copyTo(tables.ego_rgb, tables.ego_mask, rgb)
    tbuf = tables.ego_t.copy()
    ids = tables.base_ids.copy()
    nv = len(scene.vehicles)
    own_masks, crops_of, wheel_own = [], [], np.zeros((nv, 4), np.int64)
    all_boxes = [_vehicle_boxes(v) for v in scene.vehicles]
    if nv:
        crops = box_regions(cam, np.concatenate([b[0] for b in all_boxes]), np.concatenate([b[1] for b in all_boxes]),
                            np.concatenate([b[2] for b in all_boxes])).reshape(nv, 7, 4)
    for i, v in enumerate(scene.vehicles):
        wheel_ids = [nv + 4 * i + k for k in range(4)]
        own = _render_vehicle(tables, v, i, wheel_ids, tbuf, ids, rgb, sun, wheel_own[i], crops=crops[i])
        own_masks.append(own)
        crops_of.append(crops[i])
    vehicles, wheels = [], []
    for i in range(nv):
        own = own_masks[i]
        if own is None:
            vehicles.append(ObjectStats(0, 0, None))
            wheels.extend(ObjectStats(0, 0, None) for _ in range(4))
            continue
        x0, y0, x1, y1 = crops_of[i][0]
        idc = ids[y0:y1, x0:x1]
        wid0 = nv + 4 * i
        vis = (idc == i) | ((idc >= wid0) & (idc < wid0 + 4))
        vehicles.append(ObjectStats(int(own.sum()), int(vis.sum()), _bbox(vis, x0, y0)))
        for k in range(4):
            wv = idc == wid0 + k
            wheels.append(ObjectStats(int(wheel_own[i, k]), int(wv.sum()), _bbox(wv, x0, y0)))
    return rgb, ids, vehicles, wheels


def _bbox(mask: np.ndarray, x0: int, y0: int):
    cols = np.flatnonzero(mask.any(axis=0))
    if not len(cols):
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return (x0 + int(cols[0]), y0 + int(rows[0]), x0 + int(cols[-1]) + 1, y0 + int(rows[-1]) + 1)


def noise_bank(width: int, height: int, sigma: float, seed: int = 777) -> np.ndarray:
    """Gaussian sensor noise, drawn once per process; each image takes a random window of it."""
    rng = np.random.default_rng(seed)
    return np.round(rng.normal(0, sigma, (height + NOISE_PAD, width + NOISE_PAD, 3))).astype(np.int16)


def finish(rgb: np.ndarray, rng: np.random.Generator, bank: np.ndarray, blur_sigma: float,
           exposure: float) -> np.ndarray:
    """Camera effects: exposure, lens blur and sensor noise, so that crops are not trivially clean."""
    h, w = rgb.shape[:2]
    img = cv2.GaussianBlur(rgb, (0, 0), blur_sigma) if blur_sigma > 0 else rgb
    img = cv2.convertScaleAbs(img, alpha=exposure)
    dy, dx = rng.integers(0, NOISE_PAD, 2)
    out = img.astype(np.int16) + bank[dy:dy + h, dx:dx + w]
    return np.clip(out, 0, 255).astype(np.uint8)
