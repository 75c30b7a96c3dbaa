"""One image's annotations (docs/design.md §4): the class and camera vocabulary, the ``Record`` every stage
passes around, and the ``DatasetError`` every check raises."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np

VEHICLE = 0
WHEEL = 1
CLASS_NAMES = ("vehicle", "wheel")  # index = class_id
CAMERAS = ("front", "left", "right", "rear")
ROLES = ("front", "rear")
LABELS_FILE = "labels.jsonl"


class DatasetError(ValueError):
    """A problem in a dataset, located by file, line (1-based) and field."""

    def __init__(self, file: str | os.PathLike, line: int | None, field: str, message: str):
        self.file, self.line, self.field, self.message = str(file), line, field, message
        where = f"{self.file}:{line}" if line is not None else self.file
        super().__init__(f"{where}: field '{field}': {message}")


def no_ignore_regions() -> np.ndarray:
    return np.zeros((0, 5), dtype=np.float64)


@dataclass
class Record:
    """One image's annotations. ``boxes`` is an (N, 7) float array: x1, y1, x2, y2, score, class_id, box_id.
    ``ignore`` is a (K, 5) array x1, y1, x2, y2, class_id of *ignore regions*: where an object of that class is
    visible but not annotated (the generator's: too hidden to label). Evaluations count a detection mostly inside
    one, and every claim on it, neither right nor wrong, as COCO does with its crowd regions; training never reads
    them."""

    image: str
    frame_id: int
    camera: str
    width: int
    height: int
    boxes: np.ndarray
    relations: list[tuple[int, int, str | None]]
    wheel_pairs: list[tuple[int, int]]
    scene: str = ""
    extra: dict = field(default_factory=dict)
    source: tuple[str, int] | None = None  # (file, line) the record was read from, for error messages
    ignore: np.ndarray = field(default_factory=no_ignore_regions)

    @property
    def xyxy(self) -> np.ndarray:
        return self.boxes[:, :4]

    @property
    def scores(self) -> np.ndarray:
        return self.boxes[:, 4]

    @property
    def class_ids(self) -> np.ndarray:
        return self.boxes[:, 5].astype(int)

    @property
    def box_ids(self) -> np.ndarray:
        return self.boxes[:, 6].astype(int)

    @property
    def n_vehicles(self) -> int:
        return int((self.class_ids == VEHICLE).sum())

    @property
    def n_wheels(self) -> int:
        return int((self.class_ids == WHEEL).sum())

    def owner_of(self) -> dict[int, int]:
        """wheel box_id -> vehicle box_id for every related wheel."""
        return {w: v for v, w, _ in self.relations}

    def to_json(self) -> dict:
        boxes = [
            [round(float(x1), 2), round(float(y1), 2), round(float(x2), 2), round(float(y2), 2),
             round(float(s), 4), int(c), int(b)]
            for x1, y1, x2, y2, s, c, b in self.boxes
        ]
        relations = [[v, w, r] if r is not None else [v, w] for v, w, r in self.relations]
        out = {"image": self.image, "frame_id": self.frame_id, "camera": self.camera, "scene": self.scene,
               "width": self.width, "height": self.height, "boxes": boxes, "relations": relations,
               "wheel_pairs": [list(p) for p in self.wheel_pairs]}
        if len(self.ignore):
            out["ignore"] = [[round(float(x1), 2), round(float(y1), 2), round(float(x2), 2), round(float(y2), 2), int(c)]
                             for x1, y1, x2, y2, c in self.ignore]
        out.update(self.extra)
        return out


def boxes_only(rec: Record) -> Record:
    """The record's boxes without its relations, couples or ignore regions: what a relation method gets to see."""
    return replace(rec, boxes=rec.boxes.copy(), relations=[], wheel_pairs=[], ignore=no_ignore_regions())
