"""Colour transforms shared by the detector's image augmentation and the relation network's crop augmentation."""

from __future__ import annotations

import numpy as np

# RGB -> YIQ (NTSC): Y the luma, I and Q the chroma plane a hue rotation turns
_RGB_TO_YIQ = np.array([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
_YIQ_TO_RGB = np.linalg.inv(_RGB_TO_YIQ)


def hue_rotation(turns: float | np.ndarray) -> np.ndarray:
    """The 3x3 matrix that turns an RGB colour's hue by ``turns`` of the colour circle about the grey axis
    (a rotation of YIQ's chroma plane): greys, and the luma of every colour, stay as they are. An array of
    turns gives one matrix per turn, shape (..., 3, 3)."""
    angle = 2 * np.pi * np.asarray(turns, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    rotate = np.zeros(angle.shape + (3, 3))
    rotate[..., 0, 0] = 1.0
    rotate[..., 1, 1], rotate[..., 1, 2], rotate[..., 2, 1], rotate[..., 2, 2] = c, -s, s, c
    return _YIQ_TO_RGB @ rotate @ _RGB_TO_YIQ
