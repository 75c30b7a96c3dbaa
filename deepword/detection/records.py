"""A detector's decoded detections as a WORD record: what the detector stage writes and the onnxruntime runtime
reads back (torch-free)."""

from __future__ import annotations

import numpy as np

from deepword.detection.letterbox import Letterbox, boxes_to_original
from deepword.facing import FACING_KEY
from deepword.word_format import Record

# Boxes thinner than this after clipping to the image (e.g. centred outside it) are not boxes; the WORD
# format also needs x1 < x2 after its 2-decimal rounding.
MIN_BOX_PX = 0.1


def detections_to_record(detections: np.ndarray, source: Record, box: Letterbox, score_threshold: float) -> Record:
    """(K, 6) decoded detections in network-input pixels -> a prediction record for ``source``'s image:
    boxes in original image coordinates, clipped inside it, real scores, ids 0..N-1, no relations. (K, 8): a detector
    with the facing head; each vehicle's facing vector goes to ``extra["facing"]`` (deepword/facing.py; a letterbox
    scales both axes alike, so it holds in the original image)."""
    det = detections[detections[:, 4] >= score_threshold]
    xyxy = boxes_to_original(det[:, :4], box, source.width, source.height)
    keep = (xyxy[:, 2] - xyxy[:, 0] >= MIN_BOX_PX) & (xyxy[:, 3] - xyxy[:, 1] >= MIN_BOX_PX)
    xyxy, det = xyxy[keep], det[keep]
    boxes = np.column_stack([xyxy, det[:, 4], det[:, 5], np.arange(len(det))]).reshape(-1, 7)
    extra = {}
    if detections.shape[1] >= 8:
        extra[FACING_KEY] = {str(i): [round(float(dx), 4), round(float(dy), 4)]
                             for i, (dx, dy, cls) in enumerate(zip(det[:, 6], det[:, 7], det[:, 5], strict=True))
                             if int(cls) == 0}
    return Record(image=source.image, frame_id=source.frame_id, camera=source.camera, width=source.width,
                  height=source.height, boxes=boxes, relations=[], wheel_pairs=[], scene=source.scene, extra=extra)


def renumbered(record: Record, ids: np.ndarray | None = None) -> Record:
    """The record with box ids ``ids`` (one per box; default 0..N-1 in box order, as every detection record has
    them), its facing vectors following their boxes."""
    old = record.box_ids
    record.boxes[:, 6] = np.arange(len(record.boxes)) if ids is None else ids
    facing = record.extra.get(FACING_KEY)
    if facing is not None:
        record.extra = {**record.extra, FACING_KEY: {str(int(new)): facing[str(int(o))]
                                                     for new, o in zip(record.boxes[:, 6], old, strict=True)
                                                     if str(int(o)) in facing}}
    return record
