"""The WORD-style dataset format of docs/design.md §4: the one reader, writer and validator every stage uses.

A dataset is ``<root>/labels.jsonl`` (one record per image) plus the image files the records name.
The data stage's output directory additionally holds ``dataset.json`` (where the root is) and
``splits.json`` (train/val/test and the easy/hard/mixed test subsets, as lists of image paths).

This package's names are its public API (``from deepword.word_format import Record, read_records``); its
modules hold one idea each: ``record`` (the in-memory record), ``parse`` (validation of one JSON object),
``jsonl`` (labels files), ``images`` (image files), ``splits`` (split policy), ``dataset`` (the data stage's
output directory).
"""

from deepword.word_format.dataset import Dataset, open_dataset, write_dataset_index
from deepword.word_format.images import check_image_file, check_image_files, image_size, load_image
from deepword.word_format.jsonl import read_records, write_records
from deepword.word_format.parse import REQUIRED_KEYS, parse_record
from deepword.word_format.record import (
    CAMERAS,
    CLASS_NAMES,
    LABELS_FILE,
    ROLES,
    VEHICLE,
    WHEEL,
    DatasetError,
    Record,
    boxes_only,
)
from deepword.word_format.splits import PRIOR_SPLIT, SPLITS, SUBSETS, difficulty_subsets, split_by_frame

__all__ = [
    "CAMERAS", "CLASS_NAMES", "LABELS_FILE", "PRIOR_SPLIT", "REQUIRED_KEYS", "ROLES", "SPLITS", "SUBSETS", "VEHICLE", "WHEEL",
    "Dataset", "DatasetError", "Record",
    "boxes_only", "check_image_file", "check_image_files", "difficulty_subsets", "image_size", "load_image",
    "open_dataset", "parse_record", "read_records", "split_by_frame", "write_dataset_index", "write_records",
]
