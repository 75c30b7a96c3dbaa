"""The camera's own effects on a rendered image, drawn per image: lens blur, exposure, white balance,
vignetting, sensor noise and JPEG compression. They change how the pixels look, never where objects are,
so labels are unaffected."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

NOISE_PAD = 64


def parse_range(cfg: dict, key: str, where: str, lo_bound: float | None = None) -> tuple[float, float]:
    """``cfg[key]`` as a validated (min, max); errors name ``where.key`` (the generator's config fields)."""
    value = cfg.get(key)
    if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(isinstance(v, (int, float)) for v in value):
        raise ValueError(f"{where}.{key}: expected [min, max], got {value!r}")
    lo, hi = float(value[0]), float(value[1])
    if lo > hi or (lo_bound is not None and lo < lo_bound):
        raise ValueError(f"{where}.{key}: expected min <= max{'' if lo_bound is None else f' and min >= {lo_bound}'}, "
                         f"got {value!r}")
    return lo, hi


@dataclass(frozen=True)
class SensorRanges:
    """Bounds of each effect (``data.domain.sensor``)."""

    noise_sigma: tuple[float, float]   # Gaussian noise, grey levels
    blur_sigma: tuple[float, float]    # Gaussian lens blur, pixels
    exposure: tuple[float, float]      # gain on every channel
    white_balance: float               # each channel's gain is drawn in 1 +- this
    vignetting: tuple[float, float]    # brightness lost at the image corners, share
    jpeg_prob: float                   # probability of a JPEG round trip
    jpeg_quality: tuple[int, int]

    @classmethod
    def from_cfg(cls, cfg, where: str) -> SensorRanges:
        if not isinstance(cfg, dict):
            raise ValueError(f"{where}: expected a mapping, got {cfg!r}")
        wb, prob = float(cfg.get("white_balance", 0.0)), float(cfg.get("jpeg_prob", 0.0))
        if not 0 <= wb < 1:
            raise ValueError(f"{where}.white_balance: expected a value in [0, 1), got {wb}")
        if not 0 <= prob <= 1:
            raise ValueError(f"{where}.jpeg_prob: expected a probability, got {prob}")
        q = parse_range(cfg, "jpeg_quality", where, 1)
        if q[1] > 100:
            raise ValueError(f"{where}.jpeg_quality: expected values in [1, 100], got {list(q)}")
        vig = parse_range(cfg, "vignetting", where, 0)
        if vig[1] >= 1:
            raise ValueError(f"{where}.vignetting: expected shares below 1, got {list(vig)}")
        return cls(noise_sigma=parse_range(cfg, "noise_sigma", where, 0), blur_sigma=parse_range(cfg, "blur_sigma", where, 0),
                   exposure=parse_range(cfg, "exposure", where, 0.01), white_balance=wb, vignetting=vig,
                   jpeg_prob=prob, jpeg_quality=(int(q[0]), int(q[1])))


@dataclass(frozen=True)
class SensorDraw:
    """One image's effects, as recorded in its label record (``domain.sensor``)."""

    noise_sigma: float
    blur_sigma: float
    exposure: float
    white_balance: tuple[float, float, float]
    vignetting: float
    jpeg_quality: int    # 0: no JPEG round trip

    def to_record(self) -> dict:
        out = asdict(self)
        return {k: [round(x, 3) for x in v] if isinstance(v, tuple) else round(v, 3) for k, v in out.items()}


def draw_sensor(rng: np.random.Generator, r: SensorRanges) -> SensorDraw:
    jpeg = int(rng.integers(r.jpeg_quality[0], r.jpeg_quality[1] + 1)) if rng.random() < r.jpeg_prob else 0
    return SensorDraw(noise_sigma=float(rng.uniform(*r.noise_sigma)), blur_sigma=float(rng.uniform(*r.blur_sigma)),
                      exposure=float(rng.uniform(*r.exposure)),
                      white_balance=tuple(float(g) for g in rng.uniform(1 - r.white_balance, 1 + r.white_balance, 3)),
                      vignetting=float(rng.uniform(*r.vignetting)), jpeg_quality=jpeg)


def noise_bank(width: int, height: int, seed: int = 777) -> np.ndarray:
    """Unit Gaussian noise, drawn once per process; each image takes a random band of its rows (contiguous
    in memory, so OpenCV reads it in place), scaled."""
    rng = np.random.default_rng(seed)
    return rng.normal(0, 1, (height + NOISE_PAD, width, 3)).astype(np.float32)


def corner_falloff(width: int, height: int) -> np.ndarray:
    """(H, W) float32: squared distance from the image centre, 1 at the corners (vignetting's shape)."""
    u = (np.arange(width, dtype=np.float32) + 0.5 - width / 2) / (width / 2)
    v = (np.arange(height, dtype=np.float32) + 0.5 - height / 2) / (height / 2)
    return ((u[None] ** 2 + v[:, None] ** 2) / 2).astype(np.float32)


def apply_sensor(rgb: np.ndarray, s: SensorDraw, rng: np.random.Generator, bank: np.ndarray,
                 falloff: np.ndarray) -> np.ndarray:
    """Blur, then per-pixel gain (exposure x white balance x vignetting), noise, and a JPEG round trip."""
    h, w = rgb.shape[:2]
    img = cv2.GaussianBlur(rgb, (0, 0), s.blur_sigma) if s.blur_sigma > 0.05 else rgb
    vignette = 1.0 - s.vignetting * falloff
    gain = cv2.merge([vignette * float(s.exposure * g) for g in s.white_balance])
    dy = int(rng.integers(0, NOISE_PAD))
    lit = cv2.multiply(img, gain, dtype=cv2.CV_32F)
    noise = bank[dy:dy + h] if bank.shape[1] == w else np.ascontiguousarray(bank[dy:dy + h, :w])  # rigs vary in size
    out = cv2.add(cv2.scaleAdd(noise, float(s.noise_sigma), lit), 0.0, dtype=cv2.CV_8U)  # rounds, saturates
    if s.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, s.jpeg_quality])
        if not ok:
            raise RuntimeError("OpenCV could not JPEG-encode a rendered image")
        out = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return out
