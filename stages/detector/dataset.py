"""A torch Dataset turning WORD records into letterboxed network inputs and CenterNet targets.

Each image is decoded and letterboxed to the network input size once and kept in memory (uint8) for
the dataset's lifetime, so epochs pay neither the PNG decode nor the resize; the training's data module does
it for every image before training (``preload``), so that loader worker processes share one copy. Training items are
then augmented on that small uint8 image: for a share of them a mosaic of four images (``mosaic``), for the others
a horizontal flip and a random scale (multi-scale training); then an
optional random crop of ``crop`` = (width, height) (CenterNet's random-crop augmentation: the network is
fully convolutional, so it trains on crops and still runs on the whole letterboxed image at inference, where
small wheels keep the pixels of the full input scale; a rescaled image without a crop is cropped or padded
back to the input size), then photometric jitter and sensor effects on the crop only.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from deepword.detection.letterbox import PAD_VALUE, boxes_to_input, letterbox_for, letterbox_image
from deepword.facing import box_facings
from deepword.word_format import Record, load_image
from stages.detector.augment import (
    crop_or_pad,
    flip_image,
    flip_record,
    photometric_jitter,
    rescale,
    rescaled_size,
    resized_region,
    sensor_effects,
)
from stages.detector.model import CLASS_NAMES, DOWN_RATIO
from stages.detector.targets import centernet_targets, facing_targets, ttfnet_box_targets


def box_labels(record: Record, facings: np.ndarray, flipped: bool) -> np.ndarray:
    """(N, 3) per box: class id, facing x, facing y; a mirrored image's facings point the other way in x."""
    facings = np.asarray(facings, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([record.class_ids, -facings[:, 0] if flipped else facings[:, 0], facings[:, 1]])


def max_objects_of(records: list[Record]) -> int:
    """The most boxes any record has (at least 1): the padded length of the per-object targets."""
    return max([len(r.boxes) for r in records] + [1])


def crop_boxes(xyxy: np.ndarray, x0: int, y0: int, width: int, height: int,
               min_visible: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N, 4) seen through the window ``[x0, x0 + width) x [y0, y0 + height)``: shifted into the window,
    clipped to it, and kept (mask ``keep``) only where at least ``min_visible`` of their area is inside --
    a sliver of a vehicle at the crop border is no vehicle to learn from. Returns (kept boxes, keep)."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4)
    shifted = xyxy - np.array([x0, y0, x0, y0], dtype=np.float64)
    clipped = shifted.copy()
    clipped[:, [0, 2]] = clipped[:, [0, 2]].clip(0, width)
    clipped[:, [1, 3]] = clipped[:, [1, 3]].clip(0, height)
    area = (shifted[:, 2] - shifted[:, 0]) * (shifted[:, 3] - shifted[:, 1])
    visible = (clipped[:, 2] - clipped[:, 0]) * (clipped[:, 3] - clipped[:, 1])
    keep = (visible > 0) & (visible >= min_visible * area)
    return clipped[keep], keep


class CenterNetDataset(Dataset):
    """Items: ``image`` (H, W, 3) uint8 RGB (``lightning.batch_to_input`` makes the network input), targets
    ``hm wh reg ind mask`` (see ``centernet_targets``), with ``regression="ttfnet"`` also ``box box_weight``
    (``ttfnet_box_targets``), ``facing facing_mask`` (``facing_targets``: read only by a detector with the facing
    head), and ``index`` of the record. ``augment`` (flip probability, jitter strengths,
    optional ``crop`` [w, h] and ``crop_min_visible``) or None for evaluation (the whole letterboxed image)."""

    def __init__(self, root: str | Path, records: list[Record], input_width: int, input_height: int,
                 max_objects: int, augment: dict | None = None, min_overlap: float = 0.7,
                 regression: str = "centernet"):
        self.root, self.records, self.regression = Path(root), records, regression
        self.input_width, self.input_height = input_width, input_height
        self.max_objects, self.augment, self.min_overlap = max_objects, augment, min_overlap
        self.crop = tuple(augment["crop"]) if augment and augment.get("crop") else None
        if self.crop and (self.crop[0] > input_width or self.crop[1] > input_height):
            raise ValueError(f"detector.augment.crop={list(self.crop)} is larger than the input size "
                             f"{input_width}x{input_height}")
        if augment and augment.get("mosaic", 0.0) > 0:
            self.max_objects = 4 * max_objects  # a mosaic holds up to four images' boxes
        # Switched off for the last epochs by ``lightning.CloseMosaic``; in shared memory so that loader workers
        # (forked once, persistent) see the switch too.
        self.mosaic_open = torch.ones((), dtype=torch.bool).share_memory_()
        self._cache: dict[int, tuple[np.ndarray, Record, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.records)

    def letterboxed(self, index: int) -> tuple[np.ndarray, Record, np.ndarray]:
        """The record's image letterboxed to the input size (uint8, cached), the record of that image (boxes in input
        pixels, width and height the input size) and its boxes' facing vectors (``deepword.facing.box_facings``: (N, 2), NaN
        where unknown; a letterbox scales both axes alike, so they hold in the input too)."""
        if index not in self._cache:
            self._cache[index] = self._letterbox_uncached(index)
        return self._cache[index]

    def preload(self, threads: int = 1) -> None:
        """Decode and letterbox every image now, ``threads`` at a time (OpenCV releases the GIL), instead of in the
        first epoch. Loader worker processes forked afterwards share this one cache (copy-on-write, never
        written); left to fill it themselves, each worker decoded every image it was handed and kept its own copy
        of them all: on the full profile up to 10 x 5.8 GB and most images decoded ten times. A bad image file
        is reported before the first training step."""
        from concurrent.futures import ThreadPoolExecutor

        missing = [i for i in range(len(self.records)) if i not in self._cache]
        with ThreadPoolExecutor(max_workers=max(1, int(threads))) as pool:
            for i, item in zip(missing, pool.map(self._letterbox_uncached, missing), strict=True):
                self._cache[i] = item

    def hold(self, index: int, image: np.ndarray) -> None:
        """Use ``image`` (decoded, of the record's size) for the record at ``index`` instead of reading its file: the
        plan-time probe's synthetic images (stages/estimate)."""
        self._cache[index] = self._letterboxed(image, self.records[index])

    def _letterbox_uncached(self, index: int) -> tuple[np.ndarray, Record, np.ndarray]:
        record = self.records[index]
        return self._letterboxed(load_image(self.root, record), record)

    def _letterboxed(self, image: np.ndarray, record: Record) -> tuple[np.ndarray, Record, np.ndarray]:
        box = letterbox_for(record.width, record.height, self.input_width, self.input_height)
        boxes = record.boxes.copy()
        boxes[:, :4] = boxes_to_input(record.xyxy, box)
        inside = dataclasses.replace(record, boxes=boxes, width=self.input_width, height=self.input_height)
        return letterbox_image(image, box), inside, box_facings(record)

    def augmented(self, image: np.ndarray, record: Record,
                  facings: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(augmented image, its boxes (N, 4), their classes, their facing vectors (N, 2)) from a letterboxed image,
        its record and its boxes' facing vectors. The boxes' labels (class, facing x, facing y) travel together, so
        that a crop's or a mosaic's dropped boxes drop their facings too."""
        # Drawn from torch's generator so that Lightning's seed_everything (and its per-worker seeding)
        # makes the augmentation reproducible.
        rng = np.random.default_rng(int(torch.randint(0, 2**31 - 1, ()).item()))
        aug = self.augment
        mosaic = aug.get("mosaic", 0.0)
        # no draw when off or closed: a detector configured without mosaic trains as it did before mosaic existed
        if mosaic > 0 and bool(self.mosaic_open) and rng.random() < mosaic:
            image, xyxy, labels = self.mosaic(image, record, facings, rng)  # already the training window
        else:
            image, xyxy, labels = self.flipped_rescaled(image, record, facings, rng)
            origin = self.window_origin(rng, image.shape[1], image.shape[0])
            if origin is not None:
                image, xyxy, labels = self.window(image, xyxy, labels, *origin, *self.window_size)
        image = photometric_jitter(image, rng, aug["brightness"], aug["contrast"], aug["saturation"], aug.get("hue", 0.0))
        image = sensor_effects(image, rng, aug.get("blur", 0.0), aug.get("noise", 0.0), aug.get("jpeg", 0.0),
                               aug.get("grayscale", 0.0))
        return image, xyxy, labels[:, 0].astype(int), labels[:, 1:3]

    @property
    def window_size(self) -> tuple[int, int]:
        """(width, height) of a training item: the crop, or the whole input without one."""
        return self.crop or (self.input_width, self.input_height)

    def window_origin(self, rng: np.random.Generator, width: int, height: int) -> tuple[int, int] | None:
        """Where the training window starts on a ``width`` x ``height`` image: anywhere over a larger image, the
        image anywhere inside a larger window. None, and no draw, without a crop on an image of the input size."""
        cw, ch = self.window_size
        if self.crop is None and (width, height) == (cw, ch):
            return None
        x0 = int(rng.integers(min(0, width - cw), max(0, width - cw) + 1))
        y0 = int(rng.integers(min(0, height - ch), max(0, height - ch) + 1))
        return x0, y0

    def window(self, image: np.ndarray, xyxy: np.ndarray, labels: np.ndarray, x0: int, y0: int, width: int,
               height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``width`` x ``height`` window at (x0, y0) of an image (padded where it leaves it) with the boxes seen
        through it and their labels (``box_labels``): those less than ``crop_min_visible`` inside are dropped
        (``crop_boxes``)."""
        kept, keep = crop_boxes(xyxy, x0, y0, width, height, self.augment.get("crop_min_visible", 0.5))
        return crop_or_pad(image, x0, y0, width, height, PAD_VALUE), kept, labels[keep]

    def flip_and_scale(self, rng: np.random.Generator, shrink: float = 1.0) -> tuple[bool, float]:
        """The geometric draws of one image: a horizontal flip, and a random scale times ``shrink`` (1.0, and no
        draw, when neither scales)."""
        flip = bool(rng.random() < self.augment["flip"])
        low, high = self.augment.get("scale") or (1.0, 1.0)
        if high > low or low != 1.0 or shrink != 1.0:
            # multi-scale training (CenterNet's random scale): objects at sizes between the input scale's
            # neighbours, so near and far vehicles of other lenses and image sizes are not new sizes
            return flip, float(rng.uniform(low, high)) * shrink
        return flip, 1.0

    def flipped_rescaled(self, image: np.ndarray, record: Record, facings: np.ndarray,
                         rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One image through its geometric draws (``flip_and_scale``). Returns (image, boxes, labels)."""
        flip, factor = self.flip_and_scale(rng)
        if flip:
            image, record = flip_image(image), flip_record(record)
        image, xyxy = rescale(image, record.xyxy, factor)
        return image, xyxy, box_labels(record, facings, flip)

    def mosaic(self, image: np.ndarray, record: Record, facings: np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """YOLOv4's mosaic, cut to the training window: this image and three others drawn from the dataset, each
        flipped and rescaled on its own, meet at a random point of a canvas twice the window's size, each filling
        the quadrant on its side of that point (boxes less than ``crop_min_visible`` inside their quadrant are
        dropped, as at a crop's edge); the whole is shrunk by a factor drawn from ``mosaic_scale`` (applied to
        each image as it is rescaled) and the window is cut from it as from any training image. A step then sees
        four scenes' vehicles instead of one, many of them small or cut at an edge -- the vehicles the detector
        missed most -- from the same training images (docs/detector.md, "Mosaic": +4.6 points of val vehicle
        AP@0.5).

        The canvas is never drawn whole: every draw is made first, then each image resizes only the part of it
        that shows in the window (``resized_region``; the resizes of whole images were most of a mosaic's cost)
        and its boxes follow that part's own map."""
        cw, ch = self.window_size
        low, high = self.augment.get("mosaic_scale") or (0.5, 1.0)
        shrink = float(rng.uniform(low, high))
        width, height = max(4, round(2 * cw * shrink)), max(4, round(2 * ch * shrink))
        xc = int(rng.integers(width // 4, 3 * width // 4 + 1))
        yc = int(rng.integers(height // 4, 3 * height // 4 + 1))
        others = rng.integers(0, len(self.records), 3)
        sources = [(image, record, facings)] + [self.letterboxed(int(i)) for i in others]
        draws = [self.flip_and_scale(rng, shrink) for _ in sources]
        wx0, wy0 = self.window_origin(rng, width, height) or (0, 0)
        out = np.empty((ch, cw, 3), dtype=np.uint8)
        out[:] = PAD_VALUE
        min_visible = self.augment.get("crop_min_visible", 0.5)
        boxes, labels = [np.zeros((0, 4))], [np.zeros((0, 3))]  # a window may show no box at all
        quadrants = [(0, 0, xc, yc), (xc, 0, width, yc), (0, yc, xc, height), (xc, yc, width, height)]
        for (source, source_record, source_facings), (flip, factor), (x0, y0, x1, y1) in zip(sources, draws, quadrants,
                                                                                            strict=True):
            h, w = source.shape[:2]
            pw, ph = rescaled_size(w, h, factor)
            dx = xc - pw if x0 == 0 else xc  # the piece's corner nearest the meeting point sits on it
            dy = yc - ph if y0 == 0 else yc
            # what of this piece the window shows: its quadrant, within the window and within the piece
            rx0, ry0 = max(x0, wx0, dx), max(y0, wy0, dy)
            rx1, ry1 = min(x1, wx0 + cw, dx + pw), min(y1, wy0 + ch, dy + ph)
            if rx1 <= rx0 or ry1 <= ry0:
                continue  # nothing of it shows, and none of its boxes would stay
            if flip:
                source, source_record = source[:, ::-1], flip_record(source_record)
            pixels, (sx, ox, sy, oy) = resized_region(source, (pw, ph), rx0 - dx, ry0 - dy, rx1 - dx, ry1 - dy)
            out[ry0 - wy0:ry1 - wy0, rx0 - wx0:rx1 - wx0] = pixels
            xyxy = source_record.xyxy * [sx, sy, sx, sy] + [ox + dx, oy + dy, ox + dx, oy + dy]  # canvas
            # cut at the quadrant's edges, then at the window's, as the canvas drawn whole was
            kept, keep = crop_boxes(xyxy, x0, y0, x1 - x0, y1 - y0, min_visible)
            kept, keep_window = crop_boxes(kept + [x0, y0, x0, y0], wx0, wy0, cw, ch, min_visible)
            boxes.append(kept)
            labels.append(box_labels(source_record, source_facings, flip)[keep][keep_window])
        return out, np.concatenate(boxes), np.concatenate(labels)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        image, record, facings = self.letterboxed(index)
        if self.augment is not None:
            image, xyxy, classes, facings = self.augmented(image, record, facings)
        else:
            xyxy, classes = record.xyxy, record.class_ids
        height, width = image.shape[:2]
        targets = centernet_targets(xyxy / DOWN_RATIO, classes, len(CLASS_NAMES), width // DOWN_RATIO,
                                    height // DOWN_RATIO, self.max_objects, self.min_overlap)
        targets |= facing_targets(facings, targets["mask"])
        if self.regression == "ttfnet":
            targets |= ttfnet_box_targets(xyxy, width // DOWN_RATIO, height // DOWN_RATIO, DOWN_RATIO)
        item = {k: torch.from_numpy(v) for k, v in targets.items()}
        # uint8 HWC: normalised on the whole batch in torch (``lightning.batch_to_input``), a quarter of the
        # per-image loader time on the training process when done here in numpy
        item["image"] = torch.from_numpy(np.ascontiguousarray(image))
        item["index"] = torch.tensor(index)
        return item
