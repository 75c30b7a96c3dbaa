"""The one builder of tiny drawn-scene labels for stage tests: rows of side-view cars, nearer cars lower and
larger, so vehicle boxes overlap and wheels lie inside two vehicles' boxes as in the paper's Fig. 2. Each
test folder picks its image size and car geometry (``CarRows``); the random draws are the same for all."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CarRows:
    width: int
    height: int
    car: tuple[float, float]           # vehicle box width and height at nearness 1
    nearness: tuple[float, float]      # the uniform range of a car's nearness (its size factor)
    bottom: tuple[float, float]        # box bottom = bottom[0] + bottom[1] * nearness
    overhang: float = 0.0              # share of a car that may stand outside the image (its box is clipped)
    wheel_inset: float = 0.1           # wheel boxes' outer edges from the car's ends, in car widths
    roles: bool = True                 # relations name the wheel's role (rear, front)

    def car_row(self, rng: np.random.Generator, n_cars: int,
                stray_wheel: bool = False) -> tuple[np.ndarray, list, list]:
        """Boxes, relations and couples of ``n_cars`` cars; ``stray_wheel`` adds a wheel without owner."""
        boxes, relations, pairs = [], [], []
        for _ in range(n_cars):
            s = rng.uniform(*self.nearness)
            vw, vh = self.car[0] * s, self.car[1] * s
            bottom = self.bottom[0] + self.bottom[1] * s
            x1 = rng.uniform(-self.overhang * vw, self.width - (1 - self.overhang) * vw)
            vid = len(boxes)
            boxes.append([max(x1, 0), bottom - vh, min(x1 + vw, self.width), bottom, 1.0, 0, vid])
            d = 0.42 * vh  # wheel diameter
            rear, front = x1 + self.wheel_inset * vw, x1 + (1 - self.wheel_inset) * vw  # outer edges
            wheels = (("rear", [rear, bottom - d, rear + d, bottom]), ("front", [front - d, bottom - d, front, bottom]))
            ids = []
            for role, wb in wheels:
                if wb[0] >= 0 and wb[2] <= self.width:  # a wheel outside the image is not annotated
                    ids.append(len(boxes))
                    boxes.append(wb + [1.0, 1, ids[-1]])
                    relations.append((vid, ids[-1], role if self.roles else None))
            if len(ids) == 2:
                pairs.append((ids[0], ids[1]))
        if stray_wheel:  # e.g. a spare wheel lying around
            bid = len(boxes)
            boxes.append([self.width - 20.0, 4.0, self.width - 8.0, 16.0, 1.0, 1, bid])
        return np.array(boxes, dtype=np.float64).reshape(-1, 7), relations, pairs
