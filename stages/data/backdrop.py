"""What lies behind and under the objects: the sky (gradients, flat colours, clouds), a skyline of buildings
and trees on a distant ring, and the ground as a top-down texture (asphalt, concrete, gravel, brick
pavers, grass) carrying the markings and the shadows cast by vehicles and props.

Photographic ground textures are scikit-image's bundled samples (brick, grass, gravel: installed with the
package, never downloaded); the others are filtered noise. Every texture is prepared once per process
(``GroundBank``); a frame takes a shifted copy, tinted by its own colour and light.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import cv2
import numpy as np

SKIES = ("clear", "overcast", "clouds", "dusk", "tinted")
GROUNDS = ("asphalt", "concrete", "gravel", "brick", "grass")
TEX_RES = 0.05     # ground texture: metres per texel
TEX_HALF = 32.0    # the texture covers +-32 m around the ego
SKYLINE_R = 70.0   # distance of the backdrop (buildings, trees) around the scene
SKYLINE_BINS = 72  # 5 degree sectors of the skyline

# ground base colours (RGB 0..1) per family; each frame scales and jitters its family's colour
GROUND_COLOURS = {"asphalt": (0.34, 0.34, 0.35), "concrete": (0.6, 0.59, 0.56), "gravel": (0.55, 0.5, 0.44),
                  "brick": (0.55, 0.36, 0.3), "grass": (0.3, 0.45, 0.2)}
# how many metres one photograph of scikit-image's spans on the ground
PHOTO_SPAN_M = {"gravel": 3.0, "brick": 5.0, "grass": 4.0}


def _photo(name: str) -> np.ndarray:
    from skimage import data  # deferred: only generator processes load scikit-image

    return getattr(data, name)()


def _tile(img: np.ndarray, span_m: float, n: int) -> np.ndarray:
    """Resize a photograph to ``span_m`` metres of texels and tile it over n x n texels."""
    side = max(8, int(round(span_m / TEX_RES)))
    small = cv2.resize(img, (side, side), interpolation=cv2.INTER_AREA)
    reps = n // side + 1
    return np.tile(small, (reps, reps))[:n, :n]


def _normalise(gray: np.ndarray, contrast: float) -> np.ndarray:
    """Grey levels centred on 128 with a standard deviation of ``contrast``."""
    g = gray.astype(np.float32)
    return np.clip(128 + (g - g.mean()) / max(float(g.std()), 1e-3) * contrast, 0, 255).astype(np.uint8)


class GroundBank:
    """Each ground family's grey texture (mean 128) over the whole ground square, built once per process."""

    def __init__(self, families: tuple[str, ...]):
        n = int(round(2 * TEX_HALF / TEX_RES))
        self.n = n
        rng = np.random.default_rng(12345)
        fine = rng.normal(0, 1, (n, n)).astype(np.float32)
        blotches = cv2.resize(rng.normal(0, 1, (n // 16, n // 16)).astype(np.float32), (n, n),
                              interpolation=cv2.INTER_CUBIC)
        self.gray = {}
        for fam in families:
            if fam == "asphalt":
                g = np.clip(128 + 9 * blotches + 5 * fine, 0, 255).astype(np.uint8)
            elif fam == "concrete":
                g = _normalise(6 * blotches + 2 * fine, 6)
            elif fam in PHOTO_SPAN_M:
                g = _normalise(_tile(_photo(fam), PHOTO_SPAN_M[fam], n), 22 if fam == "brick" else 18)
            else:
                raise ValueError(f"unknown ground family {fam!r}; known: {GROUNDS}")
            self.gray[fam] = g


@dataclass
class Look:
    """A frame's appearance outside the objects: sky, skyline, ground, sun (recorded per image)."""

    sky: str
    horizon: np.ndarray     # sky colour at the horizon (RGB 0..1)
    zenith: np.ndarray      # sky colour straight up
    cloud_cover: float      # 0: none
    cloud_shift: int        # azimuth offset (deg) of the cloud field
    ground: str
    ground_colour: np.ndarray
    ground_shift: tuple[int, int]
    marking_colour: tuple[float, float, float]
    sun: np.ndarray         # unit vector towards the sun (ego frame)
    sun_strength: float     # 1: hard shadows and lit faces; low under overcast skies
    skyline: np.ndarray     # (SKYLINE_BINS,) height (m) of the backdrop per sector, 0: open sky
    skyline_rgb: np.ndarray  # (SKYLINE_BINS, 3)
    skyline_trees: np.ndarray  # (SKYLINE_BINS,) bool: a tree line rather than a building

    def to_record(self) -> dict:
        az = math.degrees(math.atan2(self.sun[1], self.sun[0])) % 360
        el = math.degrees(math.asin(float(np.clip(self.sun[2], -1, 1))))
        return {"sky": self.sky, "ground": self.ground, "sun_azimuth_deg": round(az, 1),
                "sun_elevation_deg": round(el, 1), "sun_strength": round(self.sun_strength, 3)}


def draw_look(rng: np.random.Generator, sky: str, ground: str, sun_elevation_deg: tuple[float, float]) -> Look:
    def jitter(rgb, spread=0.05):
        return np.clip(np.asarray(rgb) + rng.uniform(-spread, spread, 3), 0, 1)

    cover, strength = 0.0, 1.0
    if sky == "clear":
        horizon, zenith = jitter((0.78, 0.82, 0.86)), jitter((0.35, 0.55, 0.88), 0.08)
    elif sky == "overcast":
        grey = rng.uniform(0.55, 0.85)
        horizon, zenith = jitter((grey, grey, grey * 1.02), 0.02), jitter((grey * 0.9,) * 3, 0.02)
        strength = rng.uniform(0.05, 0.3)
    elif sky == "clouds":
        horizon, zenith = jitter((0.78, 0.82, 0.86)), jitter((0.35, 0.55, 0.88), 0.08)
        cover, strength = rng.uniform(0.3, 0.8), rng.uniform(0.5, 1.0)
    elif sky == "dusk":
        horizon, zenith = jitter((0.95, 0.62, 0.35), 0.06), jitter((0.25, 0.25, 0.45), 0.06)
        strength = rng.uniform(0.5, 0.9)
    elif sky == "tinted":  # a flat sky of any hue
        horizon = np.array(colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.1, 0.5), rng.uniform(0.5, 0.95)))
        zenith = horizon * rng.uniform(0.85, 1.0)
    else:
        raise ValueError(f"unknown sky family {sky!r}; known: {SKIES}")
    lo, hi = sun_elevation_deg
    el = math.radians(rng.uniform(lo, min(hi, 15.0)) if sky == "dusk" and lo < 15 else rng.uniform(lo, hi))
    az = rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    colour = np.asarray(GROUND_COLOURS[ground]) * rng.uniform(0.75, 1.2) + rng.uniform(-0.03, 0.03, 3)
    heights = rng.uniform(3, 25, SKYLINE_BINS) * (rng.random(SKYLINE_BINS) < 0.8)
    trees = rng.random(SKYLINE_BINS) < 0.3
    heights[trees] = rng.uniform(5, 12, int(trees.sum()))
    facade = rng.uniform(0.3, 0.65, (SKYLINE_BINS, 1)) * rng.uniform(0.85, 1.15, (SKYLINE_BINS, 3))
    facade[trees] = np.array([0.16, 0.32, 0.14]) * rng.uniform(0.6, 1.3, (int(trees.sum()), 1))
    marking = (0.85, 0.85, 0.82) if rng.random() < 0.75 else (0.9, 0.75, 0.2)
    return Look(sky=sky, horizon=horizon, zenith=zenith, cloud_cover=cover, cloud_shift=int(rng.integers(360)),
                ground=ground, ground_colour=np.clip(colour, 0, 1),
                ground_shift=(int(rng.integers(512)), int(rng.integers(512))), marking_colour=marking, sun=sun,
                sun_strength=float(strength), skyline=heights.astype(np.float32),
                skyline_rgb=np.clip(facade, 0, 1).astype(np.float32), skyline_trees=trees)


def cloud_field(seed: int = 4242) -> np.ndarray:
    """(90, 360) float32 in [0, 1]: smooth noise over (elevation deg, azimuth deg), wrapping in azimuth."""
    rng = np.random.default_rng(seed)
    coarse = rng.random((12, 36)).astype(np.float32)
    wide = cv2.resize(np.concatenate([coarse, coarse[:, :4]], 1), (400, 90), interpolation=cv2.INTER_CUBIC)[:, :360]
    fine = cv2.resize(rng.random((30, 120)).astype(np.float32), (360, 90), interpolation=cv2.INTER_CUBIC)
    field = 0.7 * wide + 0.3 * fine
    return ((field - field.min()) / (field.max() - field.min())).astype(np.float32)


def sky_colours(look: Look, elev: np.ndarray, az_deg: np.ndarray, clouds: np.ndarray) -> np.ndarray:
    """(n, 3) float32 sky colour of rays at elevation ``elev`` (sin of the angle above the horizon, >= 0)
    and azimuth ``az_deg``."""
    t = np.sqrt(elev)[:, None]
    horizon = look.horizon.astype(np.float32)
    rgb = horizon + t * (look.zenith - look.horizon).astype(np.float32)
    if look.cloud_cover > 0:
        row = (elev * 89).astype(np.int32)
        col = (az_deg + look.cloud_shift) % 360
        c = np.clip((clouds[row, col] - np.float32(1 - look.cloud_cover)) * 4, 0, 1)[:, None]
        white = np.array([0.93, 0.93, 0.95], np.float32)
        rgb += c * (white * (0.85 + 0.15 * t) - rgb)
    return rgb


def skyline_colours(look: Look, height: np.ndarray, sector: np.ndarray, sector_frac: np.ndarray):
    """Which sky rays hit the skyline and their colour: buildings carry rows of windows, trees a rough top."""
    top = look.skyline[sector]
    trees = look.skyline_trees[sector]
    # tree lines: a bumpy top (a bump per sector); buildings: flat roofs
    top = np.where(trees, top * (0.75 + 0.25 * np.sin(sector_frac * math.pi)), top)
    hit = height < top
    rgb = look.skyline_rgb[sector[hit]].copy()
    h, frac = height[hit], sector_frac[hit]
    window = ~trees[hit] & ((h % 3.0) > 1.1) & ((h % 3.0) < 2.2) & ((frac * 6 % 1.0) > 0.35) & (h > 1.0)
    rgb[window] = rgb[window] * 0.45 + np.array([0.12, 0.16, 0.22])
    return hit, rgb


def ground_texture(bank: GroundBank, look: Look, scene) -> np.ndarray:
    """The frame's ground as a top-down RGB texture: the family's texture, markings, and the shadows of
    vehicles and props cast along the sun."""
    light = 0.45 + 0.6 * max(look.sun[2], 0) * (0.5 + 0.5 * look.sun_strength)
    gray = np.roll(bank.gray[look.ground], look.ground_shift, axis=(0, 1))
    gain = tuple(float(c * light * 2) for c in look.ground_colour) + (0.0,)  # the texture is centred on 128
    tex = cv2.multiply(cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB), gain)
    if look.ground == "concrete":  # expansion joints of slabs
        step = 4.0
        for k in np.arange(-TEX_HALF, TEX_HALF, step):
            cv2.line(tex, _px(k, -TEX_HALF), _px(k, TEX_HALF), (40, 40, 40), 1, cv2.LINE_AA, shift=4)
            cv2.line(tex, _px(-TEX_HALF, k), _px(TEX_HALF, k), (40, 40, 40), 1, cv2.LINE_AA, shift=4)
    for m in scene.markings:
        paint = look.marking_colour if m.colour is None else m.colour
        colour = tuple(float(c * light * 255) for c in paint)
        thick = max(1, int(round(m.width / TEX_RES)))
        p0, p1 = np.array(m.p0, float), np.array(m.p1, float)
        length = np.linalg.norm(p1 - p0)
        if m.dash > 0:
            step = (p1 - p0) / length
            segs = [(p0 + step * s, p0 + step * min(s + m.dash, length)) for s in np.arange(0, length, 2.5 * m.dash)]
        else:
            segs = [(p0, p1)]
        for a, b in segs:
            cv2.line(tex, _px(*a), _px(*b), colour, thick, cv2.LINE_AA, shift=4)
    shade = np.full(gray.shape, 255, np.uint8)
    cast = _cast_offset(look)
    dark = int(round(255 - 130 * look.sun_strength))
    for v in scene.vehicles:
        _shadow(shade, v.x, v.y, v.yaw, v.length / 2, v.width / 2, v.height * 0.75, cast, dark)
    for p in scene.props:
        for b in p.boxes:
            top = float(b.centre[2] + b.half[2])
            if top > 0.3:  # kerbs and cone bases cast nothing worth drawing
                _shadow(shade, float(b.centre[0]), float(b.centre[1]), p.yaw, float(b.half[0]), float(b.half[1]),
                        top, cast, dark)
    for v in scene.vehicles:  # the dark core under every body, whatever the light
        _fill(shade, v.x, v.y, v.yaw, v.length / 2 + 0.05, v.width / 2 + 0.05, None, 125)
    shade = cv2.GaussianBlur(shade, (0, 0), 2.0)
    return cv2.multiply(tex, cv2.cvtColor(shade, cv2.COLOR_GRAY2RGB), scale=1 / 255)


def _px(x, y):
    """Metres -> texel, fixed point with 4 fractional bits (cv2 ``shift=4``)."""
    return int(round((x + TEX_HALF) / TEX_RES * 16)), int(round((TEX_HALF - y) / TEX_RES * 16))


def _cast_offset(look: Look) -> np.ndarray:
    """Ground displacement (m) of a shadow per metre of height: away from the sun, longer when it is low."""
    horiz = np.hypot(look.sun[0], look.sun[1])
    return -look.sun[:2] / max(horiz, 1e-6) * min(horiz / max(look.sun[2], 0.2), 4.0)


def _corners(x, y, yaw, hx, hy) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]]) @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def _fill(shade, x, y, yaw, hx, hy, offset, value):
    pts = _corners(x, y, yaw, hx, hy)
    if offset is not None:
        pts = cv2.convexHull(np.concatenate([pts, pts + offset]).astype(np.float32))[:, 0]
    poly = np.array([_px(px, py) for px, py in pts], np.int32)
    cv2.fillConvexPoly(shade, poly, value, cv2.LINE_AA, shift=4)


def _shadow(shade, x, y, yaw, hx, hy, height, cast, value):
    _fill(shade, x, y, yaw, hx, hy, cast * height, value)
