"""Fig. 5-style overlays of test images where the methods disagree: ground truth and each method side by
side, so a reader sees at a glance which wheel each rule gave to which vehicle (on ground-truth boxes, or end to
end on the detector's boxes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepword.metrics import score_image
from deepword.overlay import contact_sheet, draw_relations
from deepword.word_format import Record, load_image


def wrong_wheels(gt: Record, pred: Record, min_box_px: float = 0.0, match_iou: float = 0.5) -> tuple[int, int]:
    """(evaluated wheels given a wrong owner, evaluated wheels) of one prediction (§7 wheel_acc's counts)."""
    c = score_image(gt, pred, min_box_px, match_iou)
    return c.wheels - c.wheels_correct, c.wheels


def disagreements(gts: list[Record], preds: dict[str, dict[str, Record]], limit: int, min_box_px: float = 0.0,
                  match_iou: float = 0.5) -> list[Record]:
    """Ground-truth records where the methods' owner maps differ, the most wrong wheels over all methods first
    (then the most distinct answers). The methods share each image's boxes, so their owner maps compare
    directly; wrong wheels are scored against the ground truth through the box matching."""
    ranked = []
    for gt in gts:
        answers = [p[gt.image] for p in preds.values() if gt.image in p]
        n_distinct = len({frozenset(a.owner_of().items()) for a in answers})
        if n_distinct > 1:
            n_wrong = sum(wrong_wheels(gt, a, min_box_px, match_iou)[0] for a in answers)
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


    x1, y1, x2, y2 = region
    img = np.ascontiguousarray(draw_relations(rgb.copy(), rec)[y1:y2, x1:x2])
    scale = height / img.shape[0]
    img = cv2.resize(img, (max(int(round(img.shape[1] * scale)), 1), height), interpolation=cv2.INTER_LINEAR)
    bar = np.full((22, img.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(bar, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar, img], axis=0)


def write_gallery(out_dir: Path, root: Path, gts: list[Record], preds: dict[str, dict[str, Record]],
                  limit: int, min_box_px: float = 0.0, match_iou: float = 0.5) -> list[Path]:
    """One PNG per chosen image, cropped to its objects: ground truth, then every method on its boxes (titled
    with its wrong wheels; on detected boxes, boxes matched to the ground truth at ``match_iou``), tiled left to
    right and top to bottom."""
    import cv2


    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for k, gt in enumerate(disagreements(gts, preds, limit, min_box_px, match_iou)):
        rgb = load_image(root, gt)
        region = focus_region(gt)
        panels = [_panel(rgb, gt, "ground truth", region)]
        for name, p in preds.items():
            if gt.image in p:
                wrong, wheels = wrong_wheels(gt, p[gt.image], min_box_px, match_iou)
                label = f"{name}: {wrong}/{wheels} wheels wrong"
                panels.append(_panel(rgb, p[gt.image], label, region))
        wide = panels[0].shape[1] > 1.5 * panels[0].shape[0]
        sheet = contact_sheet(panels, cols=2 if wide else len(panels))  # wide crops stack in two columns
        path = out_dir / f"{k:03d}_{Path(gt.image).stem}_{gt.camera}.png"
        cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
        written.append(path)
    return written
