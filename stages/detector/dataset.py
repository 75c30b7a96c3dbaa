"""A torch Dataset turning WORD records into letterboxed network inputs and CenterNet targets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from stages.detector.augment import flip_image, flip_record, photometric_jitter
from stages.detector.letterbox import boxes_to_input, letterbox_for, letterbox_image, normalise
from stages.detector.model import CLASS_NAMES, DOWN_RATIO
from stages.detector.targets import centernet_targets
from stages.word_format import Record, load_image


def max_objects_of(records: list[Record]) -> int:
    """The most boxes any record has (at least 1): the padded length of the per-object targets."""
    return max([len(r.boxes) for r in records] + [1])


class CenterNetDataset(Dataset):
    """Items: ``image`` (3, H, W) float, targets ``hm wh reg ind mask`` (see ``centernet_targets``) and
    ``index`` of the record. ``augment`` (flip probability and jitter strengths) or None for evaluation."""

    def __init__(self, root: str | Path, records: list[Record], input_width: int, input_height: int,
                 max_objects: int, augment: dict | None = None, min_overlap: float = 0.7):
        self.root, self.records = Path(root), records
        self.input_width, self.input_height = input_width, input_height
        self.max_objects, self.augment, self.min_overlap = max_objects, augment, min_overlap

    def __len__(self) -> int:
        return len(self.records)

    def augmented(self, record: Record, image: np.ndarray) -> tuple[Record, np.ndarray]:
        # Drawn from torch's generator so that Lightning's seed_everything (and its per-worker seeding)
        # makes the augmentation reproducible.
        rng = np.random.default_rng(int(torch.randint(0, 2**31 - 1, ()).item()))
        aug = self.augment
        if rng.random() < aug["flip"]:
            record, image = flip_record(record), flip_image(image)
        image = photometric_jitter(image, rng, aug["brightness"], aug["contrast"], aug["saturation"])
        return record, image

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        record = self.records[index]
        image = load_image(self.root, record)
        if self.augment is not None:
            record, image = self.augmented(record, image)
        box = letterbox_for(record.width, record.height, self.input_width, self.input_height)
        x = normalise(letterbox_image(image, box))
        grid_boxes = boxes_to_input(record.xyxy, box) / DOWN_RATIO
        targets = centernet_targets(grid_boxes, record.class_ids, len(CLASS_NAMES), self.input_width // DOWN_RATIO,
                                    self.input_height // DOWN_RATIO, self.max_objects, self.min_overlap)
        item = {k: torch.from_numpy(v) for k, v in targets.items()}
        item["image"] = torch.from_numpy(x)
        item["index"] = torch.tensor(index)
        return item
