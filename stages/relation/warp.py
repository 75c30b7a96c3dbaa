"""Lens augmentation of the box geometry in relation training (``relation.box_warp``).

The generator's training lenses are one family (Kannala-Brandt); another family (WoodScape's radial
polynomial) maps the same rays to other image radii: at an equal field-of-view edge it shrinks the centre
and stretches the middle ring. Boxes of the same scene then have other sizes, aspect ratios and relative
positions, and a geometric gate fitted on one lens's box layouts can misjudge them. So a share ``prob``
of the training images gets its boxes moved by a random radial distortion of the normalised image plane:

    s' = s * (1 + k * (s^2 - 1)),  s = distance from a random centre near (0.5, 0.5), in units of half the
    normalised image (an ellipse on the image, as the normalised coordinates are W x H),

which fixes s = 1 (the edge of the field of view stays put) and scales the centre by (1 - k); k is drawn
in [-radial, radial]. For |k| < 0.2 it is one-to-one on the whole image (ds'/ds = 1 + k(3 s^2 - 1) > 0 up
to the corners, s^2 = 2), so a box inside another stays inside and the left-to-right order of boxes is
kept: the relations, couples and roles stay true and are not touched. A warped box is the bounding box of
its warped boundary (``SAMPLES`` points per side). The crops are not warped (they
are cut from the original image): only the box geometry the network sees (coordinate planes, pair
geometry of the GAT and the geometry gate) changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

SAMPLES = 5            # points per box side whose warped positions bound the warped box
MAX_RADIAL = 0.19      # |k| below 0.2 keeps the warp one-to-one up to the image corners


@dataclass(frozen=True)
class BoxWarpConfig:
    prob: float = 0.0      # share of training images whose boxes are warped (0: off)
    radial: float = 0.15   # k in [-radial, radial]: the centre scales by 1 - k, the field-of-view edge stays
    centre: float = 0.05   # the distortion centre moves up to this share of the image from (0.5, 0.5)

    def __post_init__(self):
        if not 0 <= self.prob <= 1:
            raise ValueError(f"relation.box_warp.prob must be a probability in [0, 1], got {self.prob}")
        if not 0 <= self.radial <= MAX_RADIAL:
            raise ValueError(f"relation.box_warp.radial must be in [0, {MAX_RADIAL}] (one-to-one warp), got {self.radial}")
        if not 0 <= self.centre <= 0.25:
            raise ValueError(f"relation.box_warp.centre must be in [0, 0.25], got {self.centre}")

    @classmethod
    def from_cfg(cls, cfg: dict | None) -> BoxWarpConfig:
        """From the plain ``relation.box_warp`` dict (absent or null: no warp)."""
        if cfg is None:
            return cls()
        unknown = sorted(set(cfg) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(f"relation.box_warp: unknown fields {unknown}; known: {sorted(cls.__dataclass_fields__)}")
        return cls(**cfg)

    @property
    def active(self) -> bool:
        return self.prob > 0 and self.radial > 0


def radial_warp(points: torch.Tensor, k: float, centre: tuple[float, float]) -> torch.Tensor:
    """(..., 2) normalised points -> the same points under s' = s (1 + k (s^2 - 1)) about ``centre``."""
    c = torch.tensor(centre, dtype=points.dtype)
    d = (points - c) / 0.5
    s2 = (d * d).sum(-1, keepdim=True)
    return c + d * (1 + k * (s2 - 1)) * 0.5


def warp_boxes(coords: torch.Tensor, k: float, centre: tuple[float, float]) -> torch.Tensor:
    """(n, 4) normalised x1, y1, x2, y2 -> the bounding boxes of their warped boundaries."""
    if len(coords) == 0:
        return coords
    t = torch.linspace(0, 1, SAMPLES, dtype=coords.dtype)
    x1, y1, x2, y2 = coords.unbind(-1)
    xs = x1[:, None] + (x2 - x1)[:, None] * t      # (n, SAMPLES) along the top and bottom sides
    ys = y1[:, None] + (y2 - y1)[:, None] * t      # along the left and right sides
    boundary = torch.cat([
        torch.stack([xs, y1[:, None].expand_as(xs)], -1), torch.stack([xs, y2[:, None].expand_as(xs)], -1),
        torch.stack([x1[:, None].expand_as(ys), ys], -1), torch.stack([x2[:, None].expand_as(ys), ys], -1)], 1)
    warped = radial_warp(boundary, k, centre)
    # not clipped to the image: with k > 0 the image corners move outward by up to 0.1 of the image, and a
    # clipped box near a corner could collapse to a line; a box a little outside [0, 1] is harmless
    return torch.cat([warped.amin(1), warped.amax(1)], -1).to(coords.dtype)


def random_box_warp(coords: torch.Tensor, cfg: BoxWarpConfig) -> torch.Tensor:
    """One image's boxes (n, 4), warped with probability ``cfg.prob`` by a random k and centre drawn from
    torch's global generator (seeded by the relation stage); otherwise returned as they are."""
    if not cfg.active or torch.rand(()) >= cfg.prob:
        return coords
    k = float((torch.rand(()) * 2 - 1) * cfg.radial)
    cx, cy = ((torch.rand(2) * 2 - 1) * cfg.centre + 0.5).tolist()
    return warp_boxes(coords, k, (cx, cy))
