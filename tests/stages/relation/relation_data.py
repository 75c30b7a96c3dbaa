"""Small drawn scenes for the relation tests: rows of side-view cars (nearer = lower and larger, so boxes
overlap and wheels lie inside two vehicles' boxes), their Records, priors as simple callables, and
SplitInputs built from them."""

from __future__ import annotations

import numpy as np

from deepword.relation_graph import InputConfig, SplitInputs, build_split
from deepword.word_format import Record
from tests.car_rows import CarRows

W, H = 192, 128


SCENES = CarRows(W, H, car=(100, 42), nearness=(0.5, 1.0), bottom=(60, 60))


def make_record(rng: np.random.Generator, index: int, n_cars: int, stray_wheel: bool = False) -> Record:
    boxes, relations, pairs = SCENES.car_row(rng, n_cars, stray_wheel)
    return Record(image=f"images/left/{index:05d}.png", frame_id=index, camera="left", width=W, height=H,
                  boxes=boxes, relations=relations, wheel_pairs=pairs, scene="parking", source=("test", index + 1))


def render(rec: Record, seed: int = 0) -> np.ndarray:
    """Cars drawn far to near (so nearer ones occlude), wheels as dark discs."""
    import cv2

    rng = np.random.default_rng(seed + rec.frame_id)
    img = np.full((H, W, 3), 150, dtype=np.uint8)
    order = sorted((b for b in rec.boxes if b[5] == 0), key=lambda b: b[3])
    for b in order:
        colour = tuple(int(c) for c in rng.integers(60, 255, 3))
        cv2.rectangle(img, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), colour, -1)
        for w in rec.boxes:
            if w[5] == 1 and b[0] <= w[0] and w[2] <= b[2] and w[3] <= b[3] + 0.5 and w[1] >= b[1]:
                c = (int((w[0] + w[2]) / 2), int((w[1] + w[3]) / 2))
                cv2.circle(img, c, max(int((w[2] - w[0]) / 2), 1), (20, 20, 20), -1)
    return img


def log_gauss(mu: float, sigma: float):
    """A prior callable: exp(-(log r - log mu)^2 / (2 sigma^2)), 1 at r = mu, in (0, 1]."""
    return lambda r: np.exp(-((np.log(np.maximum(r, 1e-9)) - np.log(mu)) ** 2) / (2 * sigma**2))


WHEEL_VEHICLE = log_gauss(3.0, 0.6)
WHEEL_WHEEL = log_gauss(4.0, 0.6)


def records(n: int, seed: int = 0, max_cars: int = 4) -> list[Record]:
    rng = np.random.default_rng(seed)
    return [make_record(rng, i, int(rng.integers(1, max_cars + 1)), stray_wheel=i % 3 == 0) for i in range(n)]


def split(recs: list[Record], cfg: InputConfig) -> SplitInputs:
    return build_split(recs, render, cfg, WHEEL_VEHICLE, WHEEL_WHEEL)
