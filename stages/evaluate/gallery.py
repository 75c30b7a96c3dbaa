"""Fig. 5-style overlays of test images where the methods disagree: ground truth and each method side by
side, so a reader sees at a glance which wheel each rule gave to which vehicle."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.evaluate.metrics import score_image
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


def _panel(rgb: np.ndarray, rec: Record, label: str) -> np.ndarray:
    import cv2

    from stages.overlay import draw_relations  # Fig. 5 drawing lives in one place

    img = np.ascontiguousarray(draw_relations(rgb.copy(), rec))
    bar = np.full((22, img.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(bar, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar, img], axis=0)


def write_gallery(out_dir: Path, root: Path, gts: list[Record], preds: dict[str, dict[str, Record]],
                  limit: int, min_box_px: float = 0.0) -> list[Path]:
    """One PNG per chosen image: ground truth, then every method (titled with its wrong wheels), left to right."""
    import cv2

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for k, gt in enumerate(disagreements(gts, preds, limit)):
        rgb = load_image(root, gt)
        panels = [_panel(rgb, gt, "ground truth")]
        for name, p in preds.items():
            if gt.image in p:
                c = score_image(gt, p[gt.image], min_box_px)
                panels.append(_panel(rgb, p[gt.image], f"{name}: {c.wheels - c.wheels_correct}/{c.wheels} wheels wrong"))
        sheet = np.concatenate(panels, axis=1)
        path = out_dir / f"{k:03d}_{Path(gt.image).stem}_{gt.camera}.png"
        cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
        written.append(path)
    return written
