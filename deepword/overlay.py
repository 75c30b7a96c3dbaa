"""Fig. 5-style drawing of owner-member relations, shared by the data visualiser, the evaluation gallery
and inference overlays: numbered boxes (vehicles and wheels in distinct colours), a red line between the
wheels of a couple, green lines rear wheel -> vehicle centre, blue front wheel -> vehicle centre (grey
when the role is unknown). Colours are RGB; images are RGB uint8.
"""

from __future__ import annotations

import cv2
import numpy as np

from deepword.word_format import VEHICLE, Record

VEHICLE_RGB = (255, 200, 0)
WHEEL_RGB = (255, 0, 255)
COUPLE_RGB = (255, 0, 0)
REAR_RGB = (0, 220, 0)
FRONT_RGB = (0, 90, 255)
UNKNOWN_ROLE_RGB = (200, 200, 200)


def _centre(box) -> tuple[int, int]:
    return int(round((box[0] + box[2]) / 2)), int(round((box[1] + box[3]) / 2))


def draw_relations(rgb: np.ndarray, record: Record) -> np.ndarray:
    """A copy of ``rgb`` with the record's boxes, ids, relations and couples drawn on it."""
    out = np.ascontiguousarray(rgb.copy())
    scale = max(out.shape[0] / 480.0, 0.5)
    thick = max(1, int(round(scale)))
    by_id = {int(b[6]): b for b in record.boxes}
    for box in record.boxes:
        colour = VEHICLE_RGB if int(box[5]) == VEHICLE else WHEEL_RGB
        x1, y1, x2, y2 = (int(round(v)) for v in box[:4])
        cv2.rectangle(out, (x1, y1), (x2 - 1, y2 - 1), colour, thick)
    for v, w, role in record.relations:
        colour = {"rear": REAR_RGB, "front": FRONT_RGB}.get(role, UNKNOWN_ROLE_RGB)
        cv2.line(out, _centre(by_id[w]), _centre(by_id[v]), colour, thick, cv2.LINE_AA)
    for a, b in record.wheel_pairs:
        cv2.line(out, _centre(by_id[a]), _centre(by_id[b]), COUPLE_RGB, thick + 1, cv2.LINE_AA)
    for box in record.boxes:
        colour = VEHICLE_RGB if int(box[5]) == VEHICLE else WHEEL_RGB
        org = (int(box[0]) + 2, max(int(box[1]) + int(11 * scale), 10))
        text = str(int(box[6]))
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4 * scale, (0, 0, 0), thick + 2, cv2.LINE_AA)
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4 * scale, colour, thick, cv2.LINE_AA)
    return out


def contact_sheet(images: list[np.ndarray], cols: int, pad: int = 4) -> np.ndarray:
    """Tile images into a grid of ``cols`` columns on a dark background. Tiles are as large as the largest
    image; images of other sizes (fisheye rigs differ) are centred in theirs, never stretched."""
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    cols = max(1, min(cols, len(images)))
    h = max(img.shape[0] for img in images)
    w = max(img.shape[1] for img in images)
    rows = (len(images) + cols - 1) // cols
    sheet = np.full((rows * (h + pad) + pad, cols * (w + pad) + pad, 3), 24, np.uint8)
    for i, img in enumerate(images):
        r, c = divmod(i, cols)
        ih, iw = img.shape[:2]
        y, x = pad + r * (h + pad) + (h - ih) // 2, pad + c * (w + pad) + (w - iw) // 2
        sheet[y:y + ih, x:x + iw] = img
    return sheet
