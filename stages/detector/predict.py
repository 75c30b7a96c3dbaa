"""Running a trained CenterNet over WORD records and writing its detections as WORD records."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.detector.letterbox import Letterbox, boxes_to_original, preprocess
from stages.word_format import Record, load_image

if TYPE_CHECKING:  # torch loads only in predict_records: the onnxruntime path uses detections_to_record
    from stages.detector.model import CenterNet

# Boxes thinner than this after clipping to the image (e.g. centred outside it) are not boxes; the WORD
# format also needs x1 < x2 after its 2-decimal rounding.
MIN_BOX_PX = 0.1


def detections_to_record(detections: np.ndarray, source: Record, box: Letterbox, score_threshold: float) -> Record:
    """(K, 6) decoded detections in network-input pixels -> a prediction record for ``source``'s image:
    boxes in original image coordinates, clipped inside it, real scores, ids 0..N-1, no relations."""
    det = detections[detections[:, 4] >= score_threshold]
    xyxy = boxes_to_original(det[:, :4], box, source.width, source.height)
    keep = (xyxy[:, 2] - xyxy[:, 0] >= MIN_BOX_PX) & (xyxy[:, 3] - xyxy[:, 1] >= MIN_BOX_PX)
    xyxy, det = xyxy[keep], det[keep]
    boxes = np.column_stack([xyxy, det[:, 4], det[:, 5], np.arange(len(det))]).reshape(-1, 7)
    return Record(image=source.image, frame_id=source.frame_id, camera=source.camera, width=source.width,
                  height=source.height, boxes=boxes, relations=[], wheel_pairs=[], scene=source.scene)


def predict_records(net: CenterNet, root: str | Path, records: list[Record], input_width: int, input_height: int,
                    k: int, score_threshold: float, batch_size: int = 16) -> list[Record]:
    """Detect on every record's image (letterboxed to the input size) and return one prediction per record."""
    import torch

    from stages.detector.decode import decode_outputs
    from stages.detector.model import DOWN_RATIO
    from stages.loader_workers import usable_cores

    net.eval()
    device = next(net.parameters()).device

    def prepared(record: Record):
        return preprocess(load_image(root, record), input_width, input_height)

    out: list[Record] = []
    # OpenCV's decoding and resizing release the GIL: threads keep a GPU (or the CPU's other cores) fed
    with ThreadPoolExecutor(max_workers=min(8, usable_cores())) as pool:
        for start in range(0, len(records), batch_size):
            chunk = records[start:start + batch_size]
            inputs, boxes = zip(*pool.map(prepared, chunk), strict=True)
            x = torch.from_numpy(np.stack(inputs)).to(device)
            with torch.no_grad():
                detections = decode_outputs(net(x), k=k, down_ratio=DOWN_RATIO).cpu().numpy()
            out += [detections_to_record(d, r, b, score_threshold)
                    for d, r, b in zip(detections, chunk, boxes, strict=True)]
    return out
