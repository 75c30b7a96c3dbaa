"""Label-consistent augmentation: a horizontal flip, a random scale, photometric jitter and sensor effects
(blur, noise, JPEG artefacts, grayscale).

Mirroring a picture of a vehicle does not change which of its wheels is the front one in 3-D, nor which
wheel belongs to which vehicle, so a flip mirrors the box coordinates and keeps relations, roles and the
rear-first order of wheel couples exactly as they were. The camera name is kept too: the detector is
camera-agnostic (one model for all four cameras) and never reads it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from deepword.colour import hue_rotation
from deepword.word_format import Record


def flip_record(record: Record) -> Record:
    """The record of the horizontally mirrored image: x1' = W - x2, x2' = W - x1; everything else kept."""
    boxes = record.boxes.copy()
    boxes[:, 0] = record.width - record.boxes[:, 2]
    boxes[:, 2] = record.width - record.boxes[:, 0]
    return dataclasses.replace(record, boxes=boxes, relations=list(record.relations),
                               wheel_pairs=list(record.wheel_pairs), extra=dict(record.extra))


def flip_image(image: np.ndarray) -> np.ndarray:
    """Mirror an HxWxC image left-right (a new contiguous array)."""
    import cv2

    return cv2.flip(image, 1) if image.dtype == np.uint8 else np.ascontiguousarray(image[:, ::-1])


_LUMA = np.array([0.299, 0.587, 0.114])


def photometric_jitter(image: np.ndarray, rng: np.random.Generator, brightness: float, contrast: float,
                       saturation: float, hue: float = 0.0) -> np.ndarray:
    """Random brightness, contrast and saturation factors in [1 - s, 1 + s] and a hue turn in [-hue, hue] of the
    colour circle (0.5: any hue), applied in a random order (CenterNet's ``color_aug`` without the PCA lighting,
    plus the hue of domain randomisation: a car's paint, the sky's tint and the ground's colour say nothing about
    where the vehicles and wheels are). Geometry is untouched, so labels stay valid.

    Contrast blends towards the mean grey of the original image, saturation towards each pixel's original grey,
    whatever ran before them (CenterNet's definition). Every step is then an affine map of the original colours,
    so the chain is composed into one 3x4 matrix and applied in a single pass (``cv2.transform``: rounded and
    saturated to uint8): four float passes over the image had been a third of the loader's time per training
    image."""
    import cv2

    colour = np.eye(3)             # the image so far = colour @ original + offset, per pixel
    offset = np.zeros(3)
    mean_grey = float(np.asarray(cv2.mean(image)[:3]) @ _LUMA)
    for i in rng.permutation(4 if hue > 0 else 3):
        if i == 0:                 # brightness
            k = rng.uniform(1 - brightness, 1 + brightness)
            colour, offset = colour * k, offset * k
        elif i == 1:               # contrast: towards the original's mean grey
            a = rng.uniform(1 - contrast, 1 + contrast)
            colour, offset = colour * a, offset * a + mean_grey * (1 - a)
        elif i == 2:               # saturation: towards each pixel's original grey
            a = rng.uniform(1 - saturation, 1 + saturation)
            colour, offset = colour * a + (1 - a) * np.outer(np.ones(3), _LUMA), offset * a
        else:                      # hue: a turn about the grey axis
            turn = hue_rotation(rng.uniform(-hue, hue))
            colour, offset = turn @ colour, turn @ offset
    return cv2.transform(image, np.hstack([colour, offset[:, None]]))


def sensor_effects(image: np.ndarray, rng: np.random.Generator, blur: float = 0.0, noise: float = 0.0,
                   jpeg: float = 0.0, grayscale: float = 0.0, max_blur_sigma: float = 1.5,
                   max_noise_std: float = 8.0, jpeg_quality: tuple[int, int] = (30, 90)) -> np.ndarray:
    """What other cameras and codecs do to a picture, each with its own probability: Gaussian blur (sigma up
    to ``max_blur_sigma`` px), additive Gaussian noise (std up to ``max_noise_std`` grey levels), a JPEG
    round trip at a quality in ``jpeg_quality`` and conversion to grey (three equal channels). A detector that
    has only seen the renderer's clean, sharp, saturated pixels keys on them; geometry is untouched. The noise
    is drawn in float32 and added by OpenCV with rounding and saturation (float64 noise was the loader's
    costliest step on the images it hit)."""
    import cv2

    out = image
    if rng.random() < blur:
        out = cv2.GaussianBlur(out, (0, 0), sigmaX=float(rng.uniform(0.3, max_blur_sigma)))
    if rng.random() < noise:
        std = rng.uniform(0.0, max_noise_std)
        out = cv2.add(out, rng.standard_normal(out.shape, dtype=np.float32) * np.float32(std), dtype=cv2.CV_8U)
    if rng.random() < jpeg:
        quality = int(rng.integers(jpeg_quality[0], jpeg_quality[1] + 1))
        ok, encoded = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
        if ok:
            out = np.ascontiguousarray(cv2.imdecode(encoded, cv2.IMREAD_COLOR)[..., ::-1])
    if rng.random() < grayscale:
        out = cv2.transform(out, np.repeat(_LUMA[None], 3, axis=0))  # every channel the pixel's grey
    return out


def rescaled_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """(width, height) of an image of this size after ``rescale`` by ``factor``."""
    if factor == 1.0:
        return width, height
    return max(1, int(round(width * factor))), max(1, int(round(height * factor)))


def rescale(image: np.ndarray, xyxy: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """The image resized by ``factor`` (area interpolation when shrinking) and its boxes scaled alike."""
    import cv2

    if factor == 1.0:
        return image, np.asarray(xyxy, dtype=np.float64)
    h, w = image.shape[:2]
    size = rescaled_size(w, h, factor)
    interp = cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR
    scale = np.array([size[0] / w, size[1] / h, size[0] / w, size[1] / h])
    return cv2.resize(image, size, interpolation=interp), np.asarray(xyxy, dtype=np.float64) * scale


def resized_region(image: np.ndarray, size: tuple[int, int], x0: int, y0: int, x1: int, y1: int
                   ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Pixels ``[y0:y1, x0:x1]`` of ``rescale``'s resize of ``image`` to ``size`` (w, h), computed from the part of
    the image they are drawn from, and the map (scale x, offset x, scale y, offset y) that takes the image's
    coordinates to those of the returned pixels' grid (x' = x * scale + offset, region origin not subtracted).

    A mosaic keeps about a quarter of each image it resizes, and the resizes were most of its cost. The part is
    cut a few output pixels wider than the region, so that the resize's edge handling stays outside it, and
    resized on its own: cv2.resize takes its scale from the sizes it is given, so the part's grid is the whole
    resize's within about a pixel, not exactly. Boxes must therefore be mapped with the returned map, not with
    ``size``: then pixels and boxes agree exactly."""
    import cv2

    h, w = image.shape[:2]
    if size == (w, h):
        return image[y0:y1, x0:x1], (1.0, 0.0, 1.0, 0.0)
    (sx0, sx1, dx0, dx1), (sy0, sy1, dy0, dy1) = (_source_cut(x0, x1, w, size[0]), _source_cut(y0, y1, h, size[1]))
    interp = cv2.INTER_AREA if size[0] < w or size[1] < h else cv2.INTER_LINEAR
    part = cv2.resize(np.ascontiguousarray(image[sy0:sy1, sx0:sx1]), (dx1 - dx0, dy1 - dy0), interpolation=interp)
    scale_x, scale_y = (dx1 - dx0) / (sx1 - sx0), (dy1 - dy0) / (sy1 - sy0)
    return (part[y0 - dy0:y1 - dy0, x0 - dx0:x1 - dx0],
            (scale_x, dx0 - sx0 * scale_x, scale_y, dy0 - sy0 * scale_y))


def _source_cut(lo: int, hi: int, n_src: int, n_out: int) -> tuple[int, int, int, int]:
    """(source start, source end, output start, output end) of one axis for ``resized_region``: the source pixels
    that output pixels [lo, hi) of a resize from n_src to n_out pixels are drawn from, three output pixels wider
    on each side (the whole axis's ends stay exact), and where they land."""
    scale = n_out / n_src
    margin = int(np.ceil(3 / scale))
    start = max(0, int(np.floor(lo / scale)) - margin)
    end = min(n_src, int(np.ceil(hi / scale)) + margin)
    out_start, out_end = int(round(start * scale)), int(round(end * scale))
    return start, end, out_start, max(out_start + 1, out_end)


def crop_or_pad(image: np.ndarray, x0: int, y0: int, width: int, height: int, fill: tuple[int, ...]) -> np.ndarray:
    """The ``width`` x ``height`` window at (x0, y0) of the image; where it leaves the image, ``fill``.
    A window may start at negative coordinates (an image smaller than the window sits inside it)."""
    h, w = image.shape[:2]
    sx0, sy0 = max(0, x0), max(0, y0)
    sx1, sy1 = min(w, x0 + width), min(h, y0 + height)
    if (sx0, sy0, sx1, sy1) == (x0, y0, x0 + width, y0 + height):  # the window lies inside the image
        return image[y0:y0 + height, x0:x0 + width].copy()
    out = np.empty((height, width, image.shape[2]), dtype=image.dtype)
    out[:] = fill
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = image[sy0:sy1, sx0:sx1]
    return out
