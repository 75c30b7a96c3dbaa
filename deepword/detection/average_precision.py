"""COCO-style average precision per class with pycocotools (the reference COCO evaluation).

torchmetrics' MeanAveragePrecision needs torchvision for boxes, which this CPU stack cannot import
(see PITFALLS), so we call pycocotools' COCOeval directly: one evaluation over all classes, then AP@0.5
and AP@[.5:.95] per class read from its precision array exactly as ``COCOeval.summarize`` does
(area range "all", the largest max-detections setting).

Ignored ground truth (``min_box_px``): as in KITTI and CityPersons, ground-truth boxes whose shorter side
is below ``min_box_px`` can be marked "ignore" -- a detection on one is neither a true nor a false
positive, and missing one costs nothing. pycocotools' only ignore flag is ``iscrowd`` (``COCOeval._prepare``
overwrites an ``ignore`` key with it), so those boxes are written as crowd regions: a detection matches
one when its intersection covers at least the IoU threshold of the *detection's* area, and a crowd region
may absorb several detections. A record's own ignore regions (``Record.ignore``: objects visible but not
annotated) are crowd regions the same way.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np

from deepword.word_format import Record


def _coco_dicts(predictions: list[Record], ground_truth: list[Record], num_classes: int,
                min_box_px: float) -> tuple[dict, list[dict]]:
    images, annotations, results = [], [], []
    for img_id, (pred, gt) in enumerate(zip(predictions, ground_truth, strict=True)):
        if pred.image != gt.image:
            raise ValueError(f"prediction {img_id} is for {pred.image!r}, ground truth for {gt.image!r}")
        images.append({"id": img_id, "width": gt.width, "height": gt.height})
        for x1, y1, x2, y2, _, cls, _ in gt.boxes:
            w, h = float(x2 - x1), float(y2 - y1)
            annotations.append({"id": len(annotations) + 1, "image_id": img_id, "category_id": int(cls),
                                "bbox": [float(x1), float(y1), w, h], "area": w * h, "iscrowd": int(min(w, h) < min_box_px)})
        for x1, y1, x2, y2, cls in gt.ignore:  # visible, not annotated: ignore regions, whatever their size
            w, h = float(x2 - x1), float(y2 - y1)
            annotations.append({"id": len(annotations) + 1, "image_id": img_id, "category_id": int(cls),
                                "bbox": [float(x1), float(y1), w, h], "area": w * h, "iscrowd": 1})
        for x1, y1, x2, y2, score, cls, _ in pred.boxes:
            results.append({"image_id": img_id, "category_id": int(cls), "score": float(score),
                            "bbox": [float(x1), float(y1), float(x2 - x1), float(y2 - y1)]})
    dataset = {"images": images, "annotations": annotations,
               "categories": [{"id": c} for c in range(num_classes)]}
    return dataset, results


def coco_average_precision(predictions: list[Record], ground_truth: list[Record],
                           class_names: tuple[str, ...] = ("vehicle", "wheel"),
                           min_box_px: float = 0.0) -> dict[str, dict[str, float]]:
    """``{class_name: {"ap50": AP@0.5, "ap": AP@[.5:.95]}}`` in percent; NaN for a class without ground truth.
    ``predictions[i]`` and ``ground_truth[i]`` describe the same image. Ground-truth boxes with a shorter
    side below ``min_box_px`` are ignored (see the module doc); 0 evaluates every box."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    dataset, results = _coco_dicts(predictions, ground_truth, len(class_names), min_box_px)
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress
        gt = COCO()
        gt.dataset = dataset
        gt.createIndex()
        dt = gt.loadRes(results) if results else COCO()
        if not results:
            dt.dataset = {"images": dataset["images"], "annotations": [], "categories": dataset["categories"]}
            dt.createIndex()
        ev = COCOeval(gt, dt, iouType="bbox")
        ev.evaluate()
        ev.accumulate()
    # precision: [iou thresholds, recall points, classes, area ranges, max-dets]; -1 where undefined.
    precision = ev.eval["precision"][:, :, :, 0, -1]
    iou50 = int(np.argmin(np.abs(ev.params.iouThrs - 0.5)))
    out = {}
    for c, name in enumerate(class_names):
        out[name] = {"ap50": _mean_defined(precision[iou50, :, c]), "ap": _mean_defined(precision[:, :, c])}
    return out


def _mean_defined(precision: np.ndarray) -> float:
    """Mean of the defined (> -1) precision values in percent, as COCOeval.summarize; NaN if none."""
    defined = precision[precision > -1]
    return 100.0 * float(defined.mean()) if defined.size else float("nan")
