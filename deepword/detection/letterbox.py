"""Letterboxing: fit an image of any size into the network's fixed input size keeping its aspect ratio,
and map boxes between the original image and the network input.

Torch-free on purpose: the onnxruntime inference path (no torch import) uses the same preprocessing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# ImageNet statistics, as CenterNet normalises its input; the padding takes the mean colour so that it
# is zero after normalisation.
MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
PAD_VALUE = tuple(int(round(255 * m)) for m in MEAN)


@dataclass(frozen=True)
class Letterbox:
    """Original ``x`` maps to input ``x * scale + pad_x`` (same for y); the image is centred."""

    scale: float
    pad_x: float
    pad_y: float
    input_width: int
    input_height: int


def letterbox_for(width: int, height: int, input_width: int, input_height: int) -> Letterbox:
    """The letterbox that fits a ``width`` x ``height`` image into ``input_width`` x ``input_height``."""
    scale = min(input_width / width, input_height / height)
    new_w, new_h = int(round(width * scale)), int(round(height * scale))
    return Letterbox(scale=scale, pad_x=(input_width - new_w) // 2, pad_y=(input_height - new_h) // 2,
                     input_width=input_width, input_height=input_height)


def letterbox_image(image: np.ndarray, box: Letterbox) -> np.ndarray:
    """Resize (area interpolation when shrinking, which keeps small wheels' edges) and pad an HxWx3 image."""
    import cv2

    h, w = image.shape[:2]
    new_w, new_h = int(round(w * box.scale)), int(round(h * box.scale))
    interp = cv2.INTER_AREA if box.scale < 1 else cv2.INTER_LINEAR
    resized = cv2.resize(image, (new_w, new_h), interpolation=interp)
    out = np.empty((box.input_height, box.input_width, 3), dtype=image.dtype)
    out[:] = PAD_VALUE
    x0, y0 = int(box.pad_x), int(box.pad_y)
    out[y0:y0 + new_h, x0:x0 + new_w] = resized
    return out


def boxes_to_input(xyxy: np.ndarray, box: Letterbox) -> np.ndarray:
    """Original-image boxes (N, 4) -> network-input boxes."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    shift = np.array([box.pad_x, box.pad_y, box.pad_x, box.pad_y])
    return xyxy * box.scale + shift


def boxes_to_original(xyxy: np.ndarray, box: Letterbox, width: int, height: int) -> np.ndarray:
    """Network-input boxes (N, 4) -> original-image boxes, clipped inside the ``width`` x ``height`` image."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    shift = np.array([box.pad_x, box.pad_y, box.pad_x, box.pad_y])
    out = (xyxy - shift) / box.scale
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, width)
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, height)
    return out


def normalise(image: np.ndarray) -> np.ndarray:
    """HxWx3 RGB uint8 -> 3xHxW float32, ImageNet-normalised (the network's input layout)."""
    x = image.astype(np.float32) / 255.0
    x = (x - MEAN) / STD
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def preprocess(image: np.ndarray, input_width: int, input_height: int) -> tuple[np.ndarray, Letterbox]:
    """An RGB uint8 image of any size -> (3xHxW float32 network input, the letterbox to map boxes back)."""
    h, w = image.shape[:2]
    box = letterbox_for(w, h, input_width, input_height)
    return normalise(letterbox_image(image, box)), box
