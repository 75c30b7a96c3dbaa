"""The facing network outside torch: each vehicle box's crop, the facing vectors between the image and the crop, and
the exported network in onnxruntime (``OnnxFacing``), which writes each vehicle's vector into a record for the
footprints' heading vote (``deepword.facing``; docs/bev.md, "Front and back").

The network learns and answers in crop pixels; ``deepword.facing_crop.to_image`` turns its answers back into image
pixels (``to_crop``, the other way, is what the facing stage trains on).
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from deepword.facing import record_facing, with_facing
from deepword.facing_crop import to_image
from deepword.footprint import FACING_SCALE_KEY
from deepword.relation_graph import crop_objects
from deepword.word_format import VEHICLE, Record

FACING_FILE = "facing.onnx"
FACING_INPUT, FACING_OUTPUT = "crops", "facing"


def vehicle_crops(rgb: np.ndarray, rec: Record, size: int, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The record's vehicle rows (M,) and their crops (M, 3, size, size) uint8."""
    rows = np.flatnonzero(rec.class_ids == VEHICLE)
    return rows, crop_objects(rgb, rec.xyxy[rows], size, margin)


class OnnxFacing:
    """The bundle's facing network (``FACING_FILE``) in onnxruntime: each vehicle box's vector, the mean of the crop's
    and its mirror image's answers (the flip it trained with), written into records with its val accuracy and the
    factor fitted on val that turns a vector's projection into log-odds (the footprints' vote)."""

    def __init__(self, bundle_dir: str | os.PathLike, meta: dict, threads: int = 1):
        """``meta``: the bundle's ``facing`` entry (``from_bundle`` reads it)."""
        from deepword.inference.runtime import ort_session

        self.input_size, self.margin = int(meta["input_size"]), float(meta["margin"])
        self.accuracy = float(meta["val_acc"]) / 100.0
        # None in a bundle exported before the scale was fitted: the vote then weighs by the accuracy alone
        self.logit_scale = None if meta.get("logit_scale") is None else float(meta["logit_scale"])
        self.session = ort_session(Path(bundle_dir) / FACING_FILE, threads)

    @classmethod
    def from_bundle(cls, bundle_dir: str | os.PathLike, threads: int = 1) -> OnnxFacing | None:
        """The bundle's facing network, or None for a bundle without one."""
        from deepword.inference.runtime import BUNDLE_FILE

        meta = json.loads((Path(bundle_dir) / BUNDLE_FILE).read_text()).get("facing")
        return cls(bundle_dir, meta, threads) if meta else None

    def crop_vectors(self, crops: np.ndarray) -> np.ndarray:
        """(M, 2) crop vectors of (M, 3, S, S) uint8 crops, flip-averaged."""
        if len(crops) == 0:
            return np.zeros((0, 2), np.float32)
        plain = self.session.run([FACING_OUTPUT], {FACING_INPUT: np.ascontiguousarray(crops)})[0]
        mirror = self.session.run([FACING_OUTPUT], {FACING_INPUT: np.ascontiguousarray(crops[..., ::-1])})[0]
        return (plain + mirror * np.array([-1.0, 1.0], np.float32)) / 2

    def vectors(self, rec: Record, rgb: np.ndarray) -> dict[int, np.ndarray]:
        """{vehicle box_id: image vector} of the record's vehicle boxes."""
        rows, crops = vehicle_crops(rgb, rec, self.input_size, self.margin)
        image = to_image(self.crop_vectors(crops), rec.xyxy[rows], self.margin)
        return {int(rec.box_ids[r]): image[k] for k, r in enumerate(rows)}

    def with_vectors(self, extra: dict, vectors: dict[int, np.ndarray]) -> dict:
        """A record's ``extra`` with ``vectors`` ({box_id: image vector}), their val accuracy
        (``deepword.facing.with_facing``) and their log-odds scale (``deepword.footprint.FACING_SCALE_KEY``)."""
        out = with_facing(extra, vectors, self.accuracy)
        return out if self.logit_scale is None else {**out, FACING_SCALE_KEY: round(self.logit_scale, 4)}

    def with_vectors_of(self, rec: Record, annotated: Record) -> Record:
        """``rec`` with the vectors this network wrote into ``annotated`` (``annotate``: a record of the same image
        whose boxes hold ``rec``'s under the same ids, e.g. the footprint point's), without running it again."""
        own = set(rec.box_ids.tolist())
        vectors = {k: np.asarray(v) for k, v in record_facing(annotated).items() if k in own}
        return replace(rec, extra=self.with_vectors(rec.extra, vectors))

    def annotate(self, rec: Record, rgb: np.ndarray) -> Record:
        """``rec`` with its vehicles' vectors (``with_vectors``)."""
        return replace(rec, extra=self.with_vectors(rec.extra, self.vectors(rec, rgb)))
