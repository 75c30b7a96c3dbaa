"""How many DataLoader worker processes a training stage (the detector's, the relation network's) uses, decided at
run time from where it trains.

``auto`` (``null`` in the configs) means none on a CPU and several on an accelerator. On a CPU the loader's
work and the training step share the same cores: on 2 cores a loader process beside the training process
made a detector epoch slower, not faster (docs/detector.md, "Epoch budget"). On a GPU the step is cheap and
the loader (decoding, augmentation, targets: ~18 ms an image at 640x480 on one core) is the training: on an
H200 with 16 cores the full profile's detector trained an epoch of ~6,300 images in 16-18 s with 10 workers
and with 14 alike, where one loader process alone would have taken ~110 s.
"""

from __future__ import annotations

import os

from stages.training.precision import trains_on_gpu

# Accelerated training measured the same with 10 and 14 workers (docs/detector.md, "On a GPU"), at a time when each
# worker decoded and kept its own copy of every image (the detector's images are now decoded once, before the
# workers are forked, and shared: CenterNetDataset.preload).
MAX_ACCELERATOR_WORKERS = 10


def usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def loader_workers(requested: int | None, accelerator: str, cores: int | None = None) -> int:
    """``requested`` when set; else 0 on a CPU and ``min(10, cores - 2)`` (at least 0) on an accelerator,
    leaving a core to the training process and one to the rest of the machine."""
    if requested is not None:
        if int(requested) < 0:
            raise ValueError(f"num_workers must be >= 0 or null (auto), got {requested}")
        return int(requested)
    if not trains_on_gpu(accelerator):
        return 0
    cores = usable_cores() if cores is None else cores
    return max(0, min(MAX_ACCELERATOR_WORKERS, cores - 2))
