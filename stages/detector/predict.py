"""Running a trained CenterNet over WORD records and writing its detections as WORD records."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deepword.detection.letterbox import preprocess
from deepword.detection.records import detections_to_record
from deepword.word_format import Record, load_image
from stages.training.loader_workers import usable_cores

if TYPE_CHECKING:
    from stages.detector.model import CenterNet

def predict_records(net: CenterNet, root: str | Path, records: list[Record], input_width: int, input_height: int,
                    k: int, score_threshold: float, batch_size: int = 16) -> list[Record]:
    """Detect on every record's image (letterboxed to the input size) and return one prediction per record."""
    import torch

    # imported here: it loads torch, which importing this module must not
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
                detections = net.decode(net(x), k).cpu().numpy()
            out += [detections_to_record(d, r, b, score_threshold)
                    for d, r, b in zip(detections, chunk, boxes, strict=True)]
    return out
