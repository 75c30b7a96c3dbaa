"""Decoded images kept for re-use within a memory budget (``deepword infer``, ``deepword tune``).

Inference reads each image several times (the detector, the relation network's crops, the facing network, the
overlays), one pass over the images after the other. Keeping every decoded image took ~1.2 GB for the ~1,000 small
SynWORD images of a quick dataset, and would take ~37 GB for 10,000 WoodScape-sized ones (1280 x 966 RGB). So the
most recently used images are kept up to a budget, and an image evicted is decoded again when a later pass asks for
it: a dataset within the budget is decoded once, a larger one a few times, in bounded memory."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable

import numpy as np

DEFAULT_BUDGET_MB = 2048   # every image of the quick profile's datasets (~1 GB) fits: they are decoded once


class DecodedImages:
    """Decoded images by key, the least recently used dropped once they hold more than ``budget_bytes`` (the one
    just asked for is always kept). ``decodes`` counts the loads, ``bytes`` what is held."""

    def __init__(self, budget_bytes: int):
        if budget_bytes < 0:
            raise ValueError(f"image memory budget: {budget_bytes} bytes, expected 0 or more")
        self.budget_bytes = int(budget_bytes)
        self.bytes = 0
        self.decodes = 0
        self._images: OrderedDict[Hashable, np.ndarray] = OrderedDict()

    def __len__(self) -> int:
        return len(self._images)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._images

    def get(self, key: Hashable, load: Callable[[], np.ndarray]) -> np.ndarray:
        """The image under ``key``, from ``load()`` where it is not held."""
        image = self._images.get(key)
        if image is not None:
            self._images.move_to_end(key)
            return image
        image = load()
        self.decodes += 1
        self.put(key, image)
        return image

    def put(self, key: Hashable, image: np.ndarray) -> None:
        """Hold ``image`` under ``key`` (the most recently used), dropping the least recently used over the budget."""
        old = self._images.pop(key, None)
        if old is not None:
            self.bytes -= old.nbytes
        self._images[key] = image
        self.bytes += image.nbytes
        while self.bytes > self.budget_bytes and len(self._images) > 1:
            _, dropped = self._images.popitem(last=False)
            self.bytes -= dropped.nbytes

    def clear(self) -> None:
        self._images.clear()
        self.bytes = 0
