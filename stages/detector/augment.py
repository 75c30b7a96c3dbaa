"""Label-consistent augmentation: a horizontal flip and photometric jitter.

Mirroring a picture of a vehicle does not change which of its wheels is the front one in 3-D, nor which
wheel belongs to which vehicle, so a flip mirrors the box coordinates and keeps relations, roles and the
rear-first order of wheel couples exactly as they were. The camera name is kept too: the detector is
camera-agnostic (one model for all four cameras) and never reads it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stages.word_format import Record


def flip_record(record: Record) -> Record:
    """The record of the horizontally mirrored image: x1' = W - x2, x2' = W - x1; everything else kept."""
    boxes = record.boxes.copy()
    boxes[:, 0] = record.width - record.boxes[:, 2]
    boxes[:, 2] = record.width - record.boxes[:, 0]
    return dataclasses.replace(record, boxes=boxes, relations=list(record.relations),
                               wheel_pairs=list(record.wheel_pairs), extra=dict(record.extra))


def flip_image(image: np.ndarray) -> np.ndarray:
    """Mirror an HxWxC image left-right."""
    return np.ascontiguousarray(image[:, ::-1])


def photometric_jitter(image: np.ndarray, rng: np.random.Generator, brightness: float, contrast: float,
                       saturation: float) -> np.ndarray:
    """Random brightness, contrast and saturation factors in [1 - s, 1 + s], applied in a random order
    (CenterNet's ``color_aug`` without the PCA lighting). Geometry is untouched, so labels stay valid."""
    x = image.astype(np.float32)
    gray = x @ np.array([0.299, 0.587, 0.114], dtype=np.float32)

    def scale_brightness(img):
        return img * rng.uniform(1 - brightness, 1 + brightness)

    def blend_contrast(img):
        a = rng.uniform(1 - contrast, 1 + contrast)
        return img * a + gray.mean() * (1 - a)

    def blend_saturation(img):
        a = rng.uniform(1 - saturation, 1 + saturation)
        return img * a + gray[..., None] * (1 - a)

    ops = [scale_brightness, blend_contrast, blend_saturation]
    for i in rng.permutation(len(ops)):
        x = ops[i](x)
    return np.clip(x, 0, 255).astype(np.uint8)
