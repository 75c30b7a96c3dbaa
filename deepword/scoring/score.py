"""Score a WORD-format predictions file against a whole WORD-format dataset (docs/design.md §7 definitions).

    python -m deepword.scoring.score --gt ROOT --pred FILE [--detections FILE] [--json OUT] [--min-box-px 8]

ROOT is a dataset directory (``labels.jsonl`` + images) or a data stage's output (``dataset.json``).
All its images are scored, split into easy / hard / mixed by ``word_format.difficulty_subsets``. An image
missing from the predictions counts as predicted with no relations; a prediction for an image the
dataset does not have, or made at another resolution (its width/height differ from the ground truth's:
its boxes would be in other pixel units), is an error. Bad input exits with code 2 and a file:line:field message.
A subset with no image (a dataset with no easy image, say) has no scores: the table says so (``easy: no images``)
and the JSON lists it under ``empty_subsets``, leaving it out of ``results``, ``relation_oracle`` and
``pair_errors`` (its §7 metrics would read 100: nothing to find and nothing found).
Beside the predictions' row, ``relation_oracle`` scores the ground truth's relations on the predicted boxes: the
ceiling those boxes leave any relation model (``deepword.scoring.pair_errors``).

``--detections FILE`` (the ``detections.jsonl`` that ``deepword infer --detect`` writes: every detection, not
only those at the operating point) adds the detector's COCO AP per class on the whole dataset, ground truth
under ``--min-box-px`` ignored as in the detector stage, and where its AP@0.5 goes
(``deepword.detection.ap_errors``). It needs pycocotools, as the pipeline does.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from deepword.detection.ap_errors import ap_error_breakdown, breakdown_markdown
from deepword.metrics import evaluated_wheel_ids, score_records
from deepword.scoring.pair_errors import RELATION_ORACLE, pair_errors_records, relation_oracle
from deepword.scoring.report import render_markdown
from deepword.scoring.roles import role_scores
from deepword.word_format import (
    CLASS_NAMES,
    LABELS_FILE,
    DatasetError,
    Record,
    boxes_only,
    difficulty_subsets,
    read_records,
)


class ScoreError(ValueError):
    """A usage problem that is not located in a file line."""


def load_ground_truth(root: Path) -> tuple[Path, list[Record]]:
    """The dataset's root and records, from a dataset folder or a data stage output folder."""
    if (root / "dataset.json").is_file():
        try:
            index = json.loads((root / "dataset.json").read_text())
        except json.JSONDecodeError as exc:
            raise DatasetError(root / "dataset.json", exc.lineno, "<json>", f"malformed JSON: {exc.msg}") from None
        data_root = (root / index["root"]).resolve()
        return data_root, read_records(data_root / index.get("labels", LABELS_FILE), root=data_root)
    if not (root / LABELS_FILE).is_file():
        raise ScoreError(f"{root}: neither {LABELS_FILE} nor dataset.json found: not a WORD-style dataset")
    return root, read_records(root / LABELS_FILE, root=root)


def load_predictions(path: Path, root: Path, gts: dict[str, Record]) -> dict[str, Record]:
    """Validated predictions by image; every image must exist in the ground truth, at its resolution."""
    if not path.is_file():
        raise ScoreError(f"{path}: predictions file not found")
    records = read_records(path, root=root, allow_empty=True)
    for rec in records:
        file, line = rec.source or (str(path), None)
        gt = gts.get(rec.image)
        if gt is None:
            raise DatasetError(file, line, "image", f"{rec.image!r} is not an image of the ground-truth dataset")
        for field, got, want in (("width", rec.width, gt.width), ("height", rec.height, gt.height)):
            if got != want:
                raise DatasetError(file, line, field, f"{got} but the ground truth's {rec.image} is {gt.width}x"
                                   f"{gt.height}: boxes must be in the ground-truth image's pixels (rescale them)")
    return {r.image: r for r in records}


def score(gt_root: Path, pred_path: Path, min_box_px: float, match_iou: float, seed: int,
          max_easy_vehicles: int = 3, detections_path: Path | None = None) -> dict:
    root, gts = load_ground_truth(gt_root)
    by_image = {r.image: r for r in gts}
    preds = load_predictions(pred_path, root, by_image)
    subsets = {s: [by_image[i] for i in images] for s, images in difficulty_subsets(gts, seed, max_easy_vehicles).items()}
    empty = [s for s, recs in subsets.items() if not recs]
    sizes = {s: {"images": len(recs), "wheels": sum(len(evaluated_wheel_ids(r, min_box_px)) for r in recs)}
             for s, recs in subsets.items()}
    subsets = {s: recs for s, recs in subsets.items() if recs}  # an empty subset has no scores, not 100s
    results = {s: score_records(recs, preds, min_box_px, match_iou).percentages() for s, recs in subsets.items()}
    errors = {s: pair_errors_records(recs, preds, min_box_px, match_iou).as_dict() for s, recs in subsets.items()}
    oracle = {image: relation_oracle(by_image[image], rec, match_iou) for image, rec in preds.items()}
    ceiling = {s: score_records(recs, oracle, min_box_px, match_iou).percentages() for s, recs in subsets.items()}
    roles = role_scores(gts, preds, match_iou)
    missing = len(set(by_image) - set(preds))
    out = {"results": results, RELATION_ORACLE: ceiling, "pair_errors": errors, "sizes": sizes, "empty_subsets": empty,
           "missing_images": missing, "roles": roles,
           "predictions": str(pred_path), "ground_truth": str(gt_root), "min_box_px": min_box_px,
           "match_iou": match_iou}
    if detections_path is not None:
        out["detector"] = detector_scores(detections_path, root, gts, min_box_px)
    return out


def roles_note(roles: dict[str, float]) -> str:
    """One line on the wheels' front / rear roles (``deepword.scoring.roles.role_scores``)."""
    n = int(roles["relations"])
    if n == 0:
        return "wheel roles: no predicted relation names a true one whose role is labelled, so none is scored"
    unnamed = int(roles["without_role"])
    return (f"wheel roles (front / rear): right for {roles['role_acc']:.1f} % of the {n} true relations found whose "
            f"role is labelled" + (f" ({unnamed} of them name no role)" if unnamed else ""))


def detector_scores(path: Path, root: Path, gts: list[Record], min_box_px: float) -> dict:
    """AP per class and where AP@0.5 goes, of every detection in ``path`` against every ground-truth image
    (an image without a detection record counts as detecting nothing)."""
    detections = load_predictions(path, root, {r.image: r for r in gts})
    truth = [boxes_only(r) for r in gts]
    found = [detections[r.image] if r.image in detections else dataclasses.replace(r, boxes=r.boxes[:0])
             for r in truth]
    breakdown = ap_error_breakdown(truth, found, CLASS_NAMES, min_box_px)  # its "as is" row is the reported AP
    ap = {name: {"ap50": row["ap50"], "ap": row["ap"]} for name, row in breakdown.items()}
    return {"detections": str(path), "ap": ap, "breakdown": breakdown,
            "missing_images": len(set(r.image for r in gts) - set(detections))}


def detector_markdown(scores: dict, min_box_px: float) -> str:
    ap = scores["ap"]
    lines = ["## Detector", "",
             f"Every detection of {scores['detections']} ({scores['missing_images']} images without one), ground "
             f"truth under {min_box_px:g} px ignored:", "",
             "| | " + " | ".join(ap) + " |", "|---|" + "---:|" * len(ap),
             "| AP@0.5 | " + " | ".join(f"{v['ap50']:.1f}" for v in ap.values()) + " |",
             "| AP@[.5:.95] | " + " | ".join(f"{v['ap']:.1f}" for v in ap.values()) + " |", ""]
    return "\n".join(lines) + "\n" + breakdown_markdown(scores["breakdown"], "whole dataset", min_box_px)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deepword score", description=__doc__.split("\n\n")[0])
    parser.add_argument("--gt", required=True, type=Path, help="WORD-style dataset root (or data stage output)")
    parser.add_argument("--pred", required=True, type=Path, help="predictions in WORD format (labels.jsonl style)")
    parser.add_argument("--detections", type=Path, help="every detection (deepword infer --detect's "
                        "detections.jsonl): adds the detector's AP per class and where it goes")
    parser.add_argument("--json", type=Path, help="also write the results as JSON here")
    parser.add_argument("--min-box-px", type=float, default=8.0, help="evaluated wheels' minimum shorter side")
    parser.add_argument("--match-iou", type=float, default=0.5, help="IoU for matching predicted to true boxes")
    parser.add_argument("--seed", type=int, default=42, help="seed of the mixed subset's sample")
    parser.add_argument("--max-easy-vehicles", type=int, default=3, help="easy: at most this many vehicles")
    parser.add_argument("--name", default="submitted", help="row name in the printed table")
    args = parser.parse_args(argv)
    try:
        out = score(args.gt, args.pred, args.min_box_px, args.match_iou, args.seed, args.max_easy_vehicles,
                    args.detections)
    except (DatasetError, ScoreError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    notes = [f"{out['missing_images']} ground-truth images had no prediction (scored as no relations)"]
    notes += [f"{s}: no images, so no scores (its columns show -)" for s in out["empty_subsets"]]
    notes += [roles_note(out["roles"])]
    print(render_markdown({"predictions": {args.name: out["results"], RELATION_ORACLE: out[RELATION_ORACLE]}},
                          out["sizes"], notes,
                          f"Scores of {args.pred} against {args.gt}",
                          errors={"predictions": {args.name: out["pair_errors"]}}))
    if "detector" in out:
        print(detector_markdown(out["detector"], args.min_box_px))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
