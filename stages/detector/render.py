"""A figure to judge the detector by eye: detections over ground truth on a few images, as one PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepword.word_format import VEHICLE, Record, load_image

GT_COLOUR = (255, 255, 255)
CLASS_COLOURS = {VEHICLE: (0, 200, 255), 1: (255, 60, 200)}  # RGB: vehicles cyan-blue, wheels magenta


def draw_detections(image: np.ndarray, prediction: Record, truth: Record, min_score: float) -> np.ndarray:
    """Ground-truth boxes in thin white, detections with score >= ``min_score`` coloured by class with
    their score."""
    import cv2

    out = image.copy()
    for x1, y1, x2, y2 in truth.xyxy:
        cv2.rectangle(out, (int(x1), int(y1)), (int(x2), int(y2)), GT_COLOUR, 1)
    for x1, y1, x2, y2, score, cls, _ in prediction.boxes:
        if score < min_score:
            continue
        colour = CLASS_COLOURS[int(cls)]
        cv2.rectangle(out, (int(x1), int(y1)), (int(x2), int(y2)), colour, 2)
        cv2.putText(out, f"{score:.2f}", (int(x1), max(10, int(y1) - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1,
                    cv2.LINE_AA)
    return out


def write_detection_grid(path: str | Path, root: str | Path, predictions: list[Record], truths: list[Record],
                         min_score: float, columns: int = 2) -> None:
    """Draw each (prediction, truth) pair and tile them into one PNG (images scaled to the first's size)."""
    import cv2

    tiles = [draw_detections(load_image(root, t), p, t, min_score) for p, t in zip(predictions, truths, strict=True)]
    h, w = tiles[0].shape[:2]
    tiles = [cv2.resize(t, (w, h)) for t in tiles]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[i:i + columns], axis=1) for i in range(0, len(tiles), columns)]
    grid = np.concatenate(rows, axis=0)
    label = f"white: ground truth; blue: vehicle, magenta: wheel detections (score >= {min_score})"
    cv2.putText(grid, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
