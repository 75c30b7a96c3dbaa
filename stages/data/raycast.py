"""Ray casting primitives: where an oriented box lands in a fisheye image, ray-box and ray-cylinder
intersections, and the depth-tested write into the frame's buffers.

Each primitive is only tested on the pixels of its projected bounding region (projected edge samples, so
the curved fisheye images of straight edges stay inside), which keeps a frame fast. The depth test gives
correct occlusion; the id buffer it writes is what the labels are made from.
"""

from __future__ import annotations

import numpy as np

from stages.data.camera import FisheyeCamera

MARGIN_PX = 3
EDGE_SAMPLES = 11


def _cube_edge_samples(n: int) -> np.ndarray:
    """(12 n, 3) points along the 12 edges of the cube [-1, 1]^3: a box's image lies inside their images' bbox."""
    t = np.linspace(-1.0, 1.0, n)
    edges = []
    for axis in range(3):
        b, c = [i for i in range(3) if i != axis]
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                p = np.zeros((n, 3))
                p[:, axis], p[:, b], p[:, c] = t, s1, s2
                edges.append(p)
    return np.concatenate(edges)


CUBE_EDGE_SAMPLES = _cube_edge_samples(EDGE_SAMPLES)


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


def intersect_box(o, d, half):
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


def face_axis(near, win):
    """Which local axis' face each winning ray entered through (0 x, 1 y, 2 z)."""
    nx, ny, nz = near[0][win], near[1][win], near[2][win]
    return np.where(nx >= ny, np.where(nx >= nz, 0, 2), np.where(ny >= nz, 1, 2))


def intersect_wheel(o, d, r, hw):
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


def local_rays(rays: np.ndarray, valid: np.ndarray, crop, R: np.ndarray):
    """The crop's ray directions in a local frame (rows x, y, z: (3, N)) and its in-FOV mask (N,)."""
    x0, y0, x1, y1 = crop
    d = rays[y0:y1, x0:x1].reshape(-1, 3)
    return R.T.astype(np.float32) @ d.T, valid[y0:y1, x0:x1].ravel()


def zwrite(crop, t, tbuf, ids, rgb, oid, colour_fn):
    """Depth-test ``t`` (flat, over ``crop``) and write id and colour where it wins; returns the hit mask.
    ``colour_fn(win)`` shades only the winning rays (``win`` flat over the crop)."""
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


def clip_crop(crop, outer):
    x0, y0 = max(crop[0], outer[0]), max(crop[1], outer[1])
    x1, y1 = min(crop[2], outer[2]), min(crop[3], outer[3])
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def or_into(own, hit, crop, outer):
    x0, y0, x1, y1 = crop
    own[y0 - outer[1]:y1 - outer[1], x0 - outer[0]:x1 - outer[0]] |= hit


def mask_bbox(mask: np.ndarray, x0: int, y0: int):
    """(x1, y1, x2, y2) of a mask's true pixels offset by (x0, y0), x2/y2 exclusive; None when empty."""
    cols = np.flatnonzero(mask.any(axis=0))
    if not len(cols):
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return (x0 + int(cols[0]), y0 + int(rows[0]), x0 + int(cols[-1]) + 1, y0 + int(rows[-1]) + 1)
