"""Appearance augmentation of the node crops in relation training (``relation.augment``).

The crops carry the look of the training renderer (its paints, skies, sensor); the relation is geometric.
Randomising the crops' appearance (photometric jitter, hue, white balance, grayscale, blur, noise, JPEG, a zoom
about the crop centre) and now and then blanking a crop's pixels makes the network lean on what transfers
to other domains. Each crop draws its own effects from torch's global generator, which the relation
stage seeds (``relation.train.seed``), so training stays reproducible. Boxes, graphs and targets are
untouched: every effect keeps the box where it is in the crop (the zoom is about the centre, small).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from deepword.colour import hue_rotation

GREY_WEIGHTS = torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)


@dataclass(frozen=True)
class AugmentConfig:
    prob: float = 0.0                  # share of crops augmented at all (0: off)
    brightness: float = 0.0            # gain in 1 +- this
    contrast: float = 0.0              # contrast factor in 1 +- this
    saturation: float = 0.0            # saturation factor in 1 +- this
    channel_gain: float = 0.0          # per-channel gain (white balance) in 1 +- this
    hue: float = 0.0                   # a turn of the crop's colours about the grey axis in +- this share of the
                                       # colour circle (0.5: any hue; deepword.colour.hue_rotation)
    grayscale: float = 0.0             # probability of a grey crop
    blur_prob: float = 0.0
    blur_sigma: tuple[float, float] = (0.5, 1.5)
    noise_prob: float = 0.0
    noise_sigma: tuple[float, float] = (2.0, 10.0)   # grey levels
    jpeg_prob: float = 0.0
    jpeg_quality: tuple[int, int] = (30, 90)
    scale: tuple[float, float] = (1.0, 1.0)          # zoom about the crop centre (> 1: closer)
    stretch: float = 0.0               # anisotropic zoom: x by e^u, y by e^-u, u in +- this (a lens's local stretch)
    drop_pixels: float = 0.0           # probability of a blank crop (the box geometry planes remain)

    def __post_init__(self):
        for name in ("prob", "grayscale", "blur_prob", "noise_prob", "jpeg_prob", "drop_pixels"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"relation.augment.{name} must be a probability in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.stretch < 0.5:
            raise ValueError(f"relation.augment.stretch must be in [0, 0.5), got {self.stretch}")
        if not 0 <= self.hue <= 0.5:
            raise ValueError(f"relation.augment.hue must be in [0, 0.5] (a share of the colour circle), got {self.hue}")
        for name in ("brightness", "contrast", "saturation", "channel_gain"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"relation.augment.{name} must be in [0, 1), got {getattr(self, name)}")
        for name in ("blur_sigma", "noise_sigma", "jpeg_quality", "scale"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"relation.augment.{name} must be [min, max] with 0 <= min <= max, got {[lo, hi]}")
        if self.scale[0] <= 0 or self.jpeg_quality[1] > 100 or self.jpeg_quality[0] < 1:
            raise ValueError("relation.augment: scale must be > 0 and jpeg_quality within [1, 100]")

    @classmethod
    def from_cfg(cls, aug: dict | None) -> AugmentConfig:
        """From the plain ``relation.augment`` dict (absent or null: no augmentation)."""
        if aug is None:
            return cls()
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(aug) - known)
        if unknown:
            raise ValueError(f"relation.augment: unknown fields {unknown}; known: {sorted(known)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in aug.items()})

    @property
    def active(self) -> bool:
        return self.prob > 0


def _uniform(n: int, lo: float, hi: float) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(n)


def _chosen(n: int, p: float) -> torch.Tensor:
    return torch.rand(n) < p


def _gaussian_kernel(sigma: float, dtype: torch.dtype) -> torch.Tensor:
    radius = max(1, int(math.ceil(2 * sigma)))
    t = torch.arange(-radius, radius + 1, dtype=dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    return k / k.sum()


def _gaussian_blur(x: torch.Tensor, sigmas: list[float]) -> torch.Tensor:
    """Crop i of ``x`` (n, C, H, W) blurred with ``sigmas[i]`` (separable, edges replicated). The crops whose
    kernels have one radius go through one grouped convolution, each channel with its own crop's kernel: the same
    sums as one crop at a time, without two convolution calls per crop."""
    out = x.clone()
    kernels = [_gaussian_kernel(s, x.dtype) for s in sigmas]
    c, h, w = x.shape[1:]
    for size in sorted({len(k) for k in kernels}):
        idx = [i for i, k in enumerate(kernels) if len(k) == size]
        radius, groups = size // 2, len(idx) * c
        k = torch.stack([kernels[i] for i in idx]).repeat_interleave(c, dim=0)   # (crops x channels, size)
        y = x[idx].reshape(1, groups, h, w)
        y = F.conv2d(F.pad(y, (radius, radius, 0, 0), mode="replicate"), k.view(groups, 1, 1, size), groups=groups)
        y = F.conv2d(F.pad(y, (0, 0, radius, radius), mode="replicate"), k.view(groups, 1, size, 1), groups=groups)
        out[idx] = y.view(len(idx), c, h, w)
    return out


@functools.lru_cache(maxsize=8)
def _identity_grid(height: int, width: int) -> torch.Tensor:
    return F.affine_grid(torch.eye(2, 3)[None], [1, 1, height, width], align_corners=False)


def _zoom_grid(sx: torch.Tensor, sy: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``F.affine_grid`` of the maps diag(sx, sy) (a zoom about the centre: no shear, no shift), as the identity's
    grid times each crop's scales: the same numbers (the product's other terms are exact zeros) without a batched
    matrix product, which took a tenth of the augmentation."""
    return _identity_grid(height, width) * torch.stack([sx, sy], dim=1)[:, None, None, :]


def _jpeg(crop: torch.Tensor, quality: int) -> torch.Tensor:
    import cv2  # deferred: only augmented training loads it here

    img = np.ascontiguousarray(crop.permute(1, 2, 0).numpy())
    ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("OpenCV could not JPEG-encode a relation crop")
    return torch.from_numpy(np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1])).permute(2, 0, 1)


def augment_crops(crops: torch.Tensor, cfg: AugmentConfig) -> torch.Tensor:
    """(k, 3, S, S) uint8 crops -> augmented (k, 3, S, S) uint8; a share ``cfg.prob`` of them is changed."""
    k = len(crops)
    if k == 0 or not cfg.active:
        return crops
    sel = _chosen(k, cfg.prob)
    if not sel.any():
        return crops
    idx = torch.nonzero(sel).flatten()
    n = len(idx)
    x = crops[idx].to(torch.float32)
    if cfg.scale != (1.0, 1.0) or cfg.stretch > 0:
        # zoom about the centre: the box stays centred, its size in the crop changes; with `stretch` the
        # width and height change in opposite directions, as a fisheye's radial and tangential scales differ
        zoom = _uniform(n, *cfg.scale)
        sx = sy = 1.0 / zoom
        if cfg.stretch > 0:
            aspect = torch.exp(_uniform(n, -cfg.stretch, cfg.stretch))
            sx, sy = sx / aspect, sy * aspect
        grid = _zoom_grid(sx, sy, x.shape[2], x.shape[3])
        x = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    if cfg.hue > 0:
        turn = torch.from_numpy(hue_rotation(_uniform(n, -cfg.hue, cfg.hue).numpy())).to(x.dtype)
        x = torch.einsum("nij,njhw->nihw", turn, x)
    grey = (x * GREY_WEIGHTS).sum(1, keepdim=True)
    if cfg.saturation > 0:
        s = _uniform(n, 1 - cfg.saturation, 1 + cfg.saturation).view(n, 1, 1, 1)
        x = grey + (x - grey) * s
    if cfg.contrast > 0:
        c = _uniform(n, 1 - cfg.contrast, 1 + cfg.contrast).view(n, 1, 1, 1)
        mean = grey.mean(dim=(2, 3), keepdim=True)
        x = mean + (x - mean) * c
    gain = _uniform(n, 1 - cfg.brightness, 1 + cfg.brightness).view(n, 1, 1, 1)
    if cfg.channel_gain > 0:
        gain = gain * _uniform(3 * n, 1 - cfg.channel_gain, 1 + cfg.channel_gain).view(n, 3, 1, 1)
    x = x * gain
    if cfg.grayscale > 0:
        g = _chosen(n, cfg.grayscale).view(n, 1, 1, 1)
        x = torch.where(g, (x * GREY_WEIGHTS).sum(1, keepdim=True).expand_as(x), x)
    if cfg.blur_prob > 0:
        blurred = torch.nonzero(_chosen(n, cfg.blur_prob)).flatten().tolist()
        if blurred:  # one sigma drawn per crop in turn, as when each crop was blurred on its own
            x[blurred] = _gaussian_blur(x[blurred], [float(_uniform(1, *cfg.blur_sigma)) for _ in blurred])
    if cfg.noise_prob > 0:
        noisy = _chosen(n, cfg.noise_prob).view(n, 1, 1, 1)
        sigma = _uniform(n, *cfg.noise_sigma).view(n, 1, 1, 1)
        x = x + torch.randn_like(x) * sigma * noisy
    out = x.round().clamp(0, 255).to(torch.uint8)
    if cfg.jpeg_prob > 0:
        lo, hi = cfg.jpeg_quality
        for i in torch.nonzero(_chosen(n, cfg.jpeg_prob)).flatten().tolist():
            out[i] = _jpeg(out[i], int(torch.randint(int(lo), int(hi) + 1, ())))
    if cfg.drop_pixels > 0:
        out[_chosen(n, cfg.drop_pixels)] = 0
    result = crops.clone()
    result[idx] = out
    return result
