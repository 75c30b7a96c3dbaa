"""Fig. 5-style overlays of test images where the methods disagree: ground truth and each method side by
side, so a reader sees at a glance which wheel each rule gave to which vehicle."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.metrics import score_image
from stages.word_format import Record, load_image


def disagreements(gts: list[Record], preds: dict[str, dict[str, Record]], limit: int) -> list[Record]:
    """Ground-truth records where the methods' owner maps differ, most disagreeing methods first."""
    ranked = []
    for gt in gts:
        owners = [frozenset(p[gt.image].owner_of().items()) for p in preds.values() if gt.image in p]
        truth = frozenset(gt.owner_of().items())
        n_distinct, n_wrong = len(set(owners)), sum(o != truth for o in owners)
        if n_distinct > 1:
            ranked.append((-n_wrong, -n_distinct, gt.image, gt))
    return [r[-1] for r in sorted(ranked, key=lambda r: r[:3])[:limit]]


def focus_region(rec: Record, margin: int = 24) -> tuple[int, int, int, int]:
    """The part of the image holding the record's boxes (plus a margin): fisheye objects are small."""
    if not len(rec.boxes):
        return 0, 0, rec.width, rec.height
    x1, y1 = np.floor(rec.xyxy[:, :2].min(axis=0)) - margin
    x2, y2 = np.ceil(rec.xyxy[:, 2:].max(axis=0)) + margin
    return int(max(x1, 0)), int(max(y1, 0)), int(min(x2, rec.width)), int(min(y2, rec.height))


def _panel(rgb: np.ndarray, rec: Record, label: str, region: tuple[int, int, int, int],
           height: int = 320) -> np.ndarray:
    import cv2

    from stages.overlay import draw_relations  # Fig. 5 drawing lives in one place (stages/overlay.py)

    x1, y1, x2, y2 = region
    img = np.ascontiguousarray(draw_relations(rgb.copy(), rec)[y1:y2, x1:x2])
    scale = height / img.shape[0]
    img = cv2.resize(img, (max(int(round(img.shape[1] * scale)), 1), height), interpolation=cv2.INTER_LINEAR)
    bar = np.full((22, img.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(bar, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar, img], axis=0)


def write_gallery(out_dir: Path, root: Path, gts: list[Record], preds: dict[str, dict[str, Record]],
                  limit: int, min_box_px: float = 0.0) -> list[Path]:
    """One PNG per chosen image, cropped to its objects: ground truth, then every method (titled with its
    wrong wheels), tiled left to right and top to bottom."""
    import cv2

    from stages.overlay import contact_sheet

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for k, gt in enumerate(disagreements(gts, preds, limit)):
        rgb = load_image(root, gt)
        region = focus_region(gt)
        panels = [_panel(rgb, gt, "ground truth", region)]
        for name, p in preds.items():
            if gt.image in p:
                c = score_image(gt, p[gt.image], min_box_px)
                label = f"{name}: {c.wheels - c.wheels_correct}/{c.wheels} wheels wrong"
                panels.append(_panel(rgb, p[gt.image], label, region))
        wide = panels[0].shape[1] > 1.5 * panels[0].shape[0]
        sheet = contact_sheet(panels, cols=2 if wide else len(panels))  # wide crops stack in two columns
        path = out_dir / f"{k:03d}_{Path(gt.image).stem}_{gt.camera}.png"
        cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
        written.append(path)
    return written
