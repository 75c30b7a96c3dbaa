"""``deepword infer``: owner-member relations of new images or of a whole WORD-style dataset, with the
exported models in onnxruntime (torch is never imported on this path).

    deepword infer IMAGE... --out DIR            detector + relation on each image
    deepword infer --dataset ROOT --out DIR      on the dataset's own boxes (the ground-truth-box setting)
    deepword infer --dataset ROOT --out DIR --detect    on detected boxes (end to end)

Options: ``--method deepword|deepword_int8|logic|logic_plus|prior|deepword_then_logic`` (default: on detected boxes
the bundle's end-to-end method, ``export.end_to_end``, by default ``deepword_then_logic``: DeepWORD with the IoU
rule's claim for each wheel DeepWORD leaves unclaimed, the rule fitted on train and stored in the bundle; on a
dataset's own boxes ``deepword``. The baselines use the thresholds the pipeline's evaluate stage fitted on train:
its ``baselines.json``); ``--calibration FILE`` (a WoodScape-style
JSON: intrinsic + extrinsic) gives loose images their camera; with it, or on a dataset whose records carry
``calibration``, each vehicle's bird's-eye-view footprint is written to the predictions' ``objects_3d`` and
a top view is drawn beside each overlay (the footprint prior comes from the run's bev stage, or ``--bev
DIR``; docs/bev.md: on detected boxes the footprints take vehicles down to the bundle's footprint point, below the
operating point, from a second pass of the relations, and a weaker vehicle's footprint is in ``footprints.jsonl``
and the top views alone). Each owned wheel's front / rear role is read from which way its vehicle faces (its footprint,
else the facing network's vector: ``deepword.wheel_roles``), not from the relation network's role head, which is near
chance; ``--roles network`` keeps the method's. ``--run RUN_ID`` picks the pipeline
run whose artifacts to use (default: the newest finished one; see ``stages.inference.resolve``), or
``--export DIR`` [``--evaluate DIR``] name the stage output directories directly.

Writes ``DIR/labels.jsonl`` (WORD-format predictions with real detector scores; image paths relative to
the dataset root, or to the images' common folder) and, per image, a Fig. 5-style overlay
``DIR/overlays/<image>.png`` (for a dataset only with ``--overlays N``) and, with footprints, each frame's fused
footprints ``DIR/footprints.jsonl`` (the images of one instant estimated and fused together exactly as the bev stage
does: its prior with the heading table, its fusion radius) and, per frame of two or more images one of which is
overlaid, the top view of the frame's fused footprints ``DIR/top_views/frame_<id>.png`` (loose images
are one frame with ``--frame`` and one ``--calibration`` file per image, each naming its camera; a recorded
drive's are a frame per instant with ``--rig DIR``, each image's camera and instant read from its path and each
camera's calibration from DIR). Wherever the detector runs it also
writes ``DIR/detections.jsonl``: every detection down to its score threshold, without relations (the
operating point cuts them for the relations; average precision needs them all). Score a dataset's
predictions with ``deepword score --gt ROOT --pred DIR/labels.jsonl [--detections DIR/detections.jsonl]``
(the second adds the detector's AP and where it goes). On a dataset each pass over the images prints progress
lines, the decoded images stay in memory between passes within ``--image-memory-mb`` (decoded again beyond it), and
``--threads N`` processes fit the frames' footprints; none of it changes a prediction. Bad input exits with code 2
and a message naming the file (and line and field for a labels file), without a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from deepword.facing import FACING_KEY
from deepword.inference.facing_net import OnnxFacing
from deepword.inference.footprints import (
    RIG_NAMING,
    CalibrationError,
    beside_top_view,
    calibration_camera,
    camera_of,
    estimate_frames,
    facing_check,
    load_fuse_radius,
    load_prior,
    read_calibration_file,
    read_rig_calibrations,
    rig_view_of,
    with_objects_3d,
    write_frame_footprints,
    write_frame_views,
)
from deepword.inference.runtime import (
    METHOD_VARIANTS,
    PRIORS_FILE,
    NoDetectorError,
    NoRuleError,
    OnnxDetector,
    bundle_method,
    end_to_end_method,
)
from deepword.overlay import draw_relations
from deepword.priors import load_priors
from deepword.progress import progress_lines
from deepword.rules.baselines import BASELINES_FILE, baseline_from_params
from deepword.rules.fallback import FALLBACKS, ClaimFallback
from deepword.scoring.score import ScoreError, load_ground_truth
from deepword.wheel_roles import ROLES_FROM_KEY, roles_from_front
from deepword.word_format import CAMERAS, DatasetError, Record, boxes_only, load_image, write_records
from stages.inference.image_cache import DEFAULT_BUDGET_MB, DecodedImages
from stages.inference.resolve import ResolveError, stage_dirs

BASELINES = ("logic", "logic_plus", "prior")
METHODS = (*METHOD_VARIANTS, *BASELINES, *FALLBACKS)
PREDICTIONS_FILE = "labels.jsonl"
DETECTIONS_FILE = "detections.jsonl"
OVERLAY_DIR = "overlays"
PROGRESS_MIN_IMAGES = 50   # a few loose photographs print no progress lines; a dataset prints one per tenth of a pass


class InferError(RuntimeError):
    """A usage or input problem reported as one line (exit code 2)."""


def read_image(path: Path) -> np.ndarray:
    """RGB uint8, or InferError naming the file."""
    import cv2

    if not path.is_file():
        raise InferError(f"{path}: image file not found")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InferError(f"{path}: cannot read the image (not a PNG/JPEG file, or corrupt)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def progress(items, total: int, desc: str, unit: str = "image"):
    """``items`` with progress lines on stderr (``deepword.progress``) where there are ``PROGRESS_MIN_IMAGES`` or
    more."""
    return progress_lines(items, total, desc, unit) if total >= PROGRESS_MIN_IMAGES else items


def image_records(paths: list[Path], camera: str, pixels: DecodedImages) -> tuple[Path, list[Record]]:
    """Records without boxes for loose images: (their common folder = the root, records); each image read once here
    (an unreadable one is an error before anything runs) and offered to ``pixels``."""
    root = Path(os.path.commonpath([str(p.resolve().parent) for p in paths]))
    records, seen = [], set()
    for i, path in enumerate(progress(paths, len(paths), "reading")):
        rgb = read_image(path)
        rel = path.resolve().relative_to(root).as_posix()
        if rel in seen:
            raise InferError(f"{path}: the same image is given twice")
        seen.add(rel)
        pixels.put(rel, rgb)
        records.append(Record(image=rel, frame_id=i, camera=camera, width=rgb.shape[1], height=rgb.shape[0],
                              boxes=np.zeros((0, 7)), relations=[], wheel_pairs=[]))
    return root, records


def rig_records(paths: list[Path], records: list[Record]) -> list[Record]:
    """``records`` (of the images ``paths``, in order) with each one's camera and frame number read from its path
    (``rig_view_of``), so that one instant's images are estimated and fused together; InferError naming the image
    where the path does not tell them, or where two images are one camera's at one instant."""
    seen: dict[tuple[str, int], Path] = {}
    out = []
    for path, rec in zip(paths, records, strict=True):
        view = rig_view_of(path)
        if view is None:
            raise InferError(f"{path}: --rig reads each image's camera and frame from its path: {RIG_NAMING}")
        if view in seen:
            raise InferError(f"{path}: the {view[0]} camera's image of frame {view[1]} again (first {seen[view]})")
        seen[view] = path
        out.append(replace(rec, camera=view[0], frame_id=view[1]))
    return out


def resolve_dirs(args, need_detector: bool) -> dict[str, Path]:
    """The export (and, for a baseline, evaluate) stage directories to use."""

    if args.export is not None:
        dirs = {"export": args.export}
        if args.evaluate is not None:
            dirs["evaluate"] = args.evaluate
        return dirs
    run_id, dirs = stage_dirs(args.run, args.tracking_uri, args.cache_dir, need_detector=need_detector)
    print(f"using the artifacts of pipeline run {run_id}", file=sys.stderr)
    return dirs


def default_method(dirs: dict[str, Path], detect: bool) -> str:
    """``--method``'s default: the bundle's end-to-end method on detected boxes, DeepWORD on given boxes (where the
    rule it falls back on adds nothing: docs/detector.md)."""

    return end_to_end_method(dirs["export"]) if detect else "deepword"


def build_method(name: str, dirs: dict[str, Path], root: Path, threads: int, load_rgb):
    """An object with ``predict(record) -> Record`` for ``name`` (DeepWORD reads images with ``load_rgb``)."""

    if name in METHOD_VARIANTS or name in FALLBACKS:
        try:
            return bundle_method(name, dirs["export"], root, threads, load_rgb)
        except NoRuleError as exc:  # a bundle from before it held its fallback rule: the evaluate stage's fit of it

            if "evaluate" not in dirs or not (dirs["evaluate"] / BASELINES_FILE).is_file():
                raise InferError(f"--method {name}: {exc}; pass --evaluate DIR (or a --run whose evaluate stage "
                                 "finished) for the evaluate stage's fit of it, or export the run again") from None
            primary, fallback = FALLBACKS[name]
            return ClaimFallback(build_method(primary, dirs, root, threads, load_rgb),
                                 build_method(fallback, dirs, root, threads, load_rgb), name)

    if "evaluate" not in dirs or not (dirs["evaluate"] / BASELINES_FILE).is_file():
        raise InferError(f"--method {name} needs the fitted baselines (the evaluate stage's {BASELINES_FILE}): "
                         "pass --evaluate DIR or a --run whose evaluate stage finished")
    params = json.loads((dirs["evaluate"] / BASELINES_FILE).read_text())
    if name not in params:
        raise InferError(f"{dirs['evaluate'] / BASELINES_FILE}: no fitted parameters for {name!r}")
    return baseline_from_params(name, params[name], load_priors(dirs["export"] / PRIORS_FILE))


def write_overlay(out_dir: Path, rgb: np.ndarray, pred: Record, frame=None) -> Path:
    """The Fig. 5-style overlay; ``frame`` (its ``deepword.inference.footprints.Frame``) adds the top view of the
    image's footprints beside it."""
    import cv2

    path = out_dir / OVERLAY_DIR / (Path(pred.image).with_suffix("").as_posix().replace("/", "__") + ".png")
    path.parent.mkdir(parents=True, exist_ok=True)
    image = draw_relations(rgb, pred)
    if frame is not None:
        image = beside_top_view(image, pred.image, frame)
    cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return path


def add_footprints(args, dirs: dict[str, Path], preds: list[Record], rgb_of, facing_net: OnnxFacing | None,
                   placed: list[Record] | None = None) -> tuple[list[Record], dict]:
    """Footprints for every prediction with a camera (``--calibration`` or the record's own), frame by frame as the
    bev stage estimates them (``estimate_frames``: one instant's images together, with the bev stage's prior and
    fusion radius, each vehicle's facing from the bundle's facing network where it has one); returns the predictions
    with ``objects_3d`` (and ``facing``) and {frame_id: Frame}. ``placed`` (one per prediction, its image's: the
    relations on the footprint point's detections, whose boxes keep the predictions' ids) is what the footprints are
    made from where given; a prediction's ``objects_3d`` names its own boxes. ``rgb_of(record)``: the image's
    pixels."""

    calibration, per_image = None, {}
    files = args.calibration or []
    if args.rig is not None:   # each image's camera named by its path, each camera's calibration from the folder
        sizes: dict[str, set] = {}
        for p in preds:
            sizes.setdefault(p.camera, set()).add((p.width, p.height))
        try:
            cals = read_rig_calibrations(args.rig, sizes)
        except CalibrationError as exc:
            raise InferError(str(exc)) from None
        per_image = {p.image: cals[p.camera] for p in preds}
    elif len(files) > 1:  # one calibration file per image, in the images' order (e.g. one frame's four cameras)
        if len(files) != len(preds) or args.dataset is not None:
            raise InferError(f"--calibration: {len(files)} files for {len(preds)} images (give one file for every "
                             "image, or one for all)")
        try:
            cals = [read_calibration_file(f, p.width, p.height) for f, p in zip(files, preds, strict=True)]
        except CalibrationError as exc:
            raise InferError(str(exc)) from None
        preds = [replace(p, camera=calibration_camera(c, f, p.camera)) if args.frame else p
                 for p, c, f in zip(preds, cals, files, strict=True)]
        per_image = {p.image: c for p, c in zip(preds, cals, strict=True)}
    elif files:
        sizes = {(p.width, p.height) for p in preds}
        try:
            calibration = read_calibration_file(files[0], *min(sizes)) if sizes else None
        except CalibrationError as exc:
            raise InferError(str(exc)) from None
        if len(sizes) > 1:
            raise InferError(f"{files[0]}: one calibration for images of {len(sizes)} different sizes")
    if calibration is None and not per_image and not any("calibration" in p.extra for p in preds):
        return preds, {}
    bev_dir = args.bev if args.bev is not None else dirs.get("bev")
    if bev_dir is None:
        why = "footprints need the footprint prior of a bev stage: pass --bev DIR or a --run whose bev stage finished"
        if args.calibration:
            raise InferError(why)
        print(f"note: no bird's-eye-view footprints ({why})", file=sys.stderr)
        return preds, {}
    try:
        prior = load_prior(bev_dir)
    except CalibrationError as exc:
        raise InferError(str(exc)) from None
    cams = {p.image: cam for p in preds if (cam := camera_of(p, per_image.get(p.image, calibration))) is not None}
    own_boxes = placed is None   # the footprints are made from the predictions themselves
    placed = preds if own_boxes else placed
    if facing_net is not None:   # each placed vehicle's facing: the footprints' heading vote (docs/bev.md)
        placed = [facing_net.annotate(p, rgb_of(p)) if p.image in cams else p
                  for p in progress(placed, len(placed), "facing network")]
        # the footprint point's boxes hold the predictions' under the same ids: their vectors are copied, not run again
        preds = placed if own_boxes else [facing_net.with_vectors_of(p, a) if p.image in cams else p
                                          for p, a in zip(preds, placed, strict=True)]
    frames = estimate_frames([(p, cams[p.image]) for p in placed if p.image in cams], prior, load_fuse_radius(bev_dir),
                             facing_net.accuracy if facing_net is not None else None,
                             progress=lambda items, n: progress(items, n, "footprints", "frame"),
                             workers=args.threads)
    check = facing_check(frames, facing_net.accuracy) if facing_net is not None else None
    if check is not None:
        print(check, file=sys.stderr)
    return [with_objects_3d(p, frames[p.frame_id]) if p.image in cams else p for p in preds], frames


def add_roles(preds: list[Record], frames: dict, facing_net: OnnxFacing | None, rgb_of) -> list[Record]:
    """The predictions with each owned wheel's role read from which way its vehicle faces
    (``deepword.wheel_roles.roles_from_front``): from its fused footprint where the image has a camera, else from the
    facing network's vector of its vehicle box, else as the relation method wrote it; a prediction neither reaches (no
    camera, no facing network) is left as it was."""
    out = []
    for pred in preds:
        frame = frames.get(pred.frame_id)
        placed = frame is not None and pred.image in frame.contacts
        if not pred.relations or (facing_net is None and not placed):
            out.append(pred)
            continue
        if facing_net is not None and FACING_KEY not in pred.extra:
            pred = facing_net.annotate(pred, rgb_of(pred))
        out.append(roles_from_front(pred, frame.fused, frame.contacts[pred.image]) if placed
                   else roles_from_front(pred))
    return out


def with_calibration(pred: Record, source: Record) -> Record:
    """``pred`` with ``source``'s ``calibration`` where it has one."""
    if "calibration" not in source.extra:
        return pred
    return replace(pred, extra={**pred.extra, "calibration": source.extra["calibration"]})


def infer(args) -> list[Record]:
    dirs = resolve_dirs(args, need_detector=args.detect or args.dataset is None)
    if args.image_memory_mb < 0:
        raise InferError(f"--image-memory-mb {args.image_memory_mb}: expected 0 or more")
    # each pass over the images (detector, relations, facing network, overlays) reads them again: kept decoded within
    # the budget, decoded again beyond it (stages/inference/image_cache.py)
    pixels = DecodedImages(args.image_memory_mb * 2**20)
    if args.dataset is not None:

        try:
            root, records = load_ground_truth(args.dataset)
        except ScoreError as exc:
            raise InferError(str(exc)) from None
        detect = args.detect
        records = [boxes_only(r) for r in records]
        overlays = args.overlays
    else:
        root, records = image_records(args.images, args.camera, pixels)
        if args.frame:  # the images are one instant's cameras: one frame
            records = [replace(r, frame_id=0) for r in records]
        elif args.rig is not None:   # a recorded drive: each image's camera and instant from its path
            records = rig_records(args.images, records)
        detect, overlays = True, len(records)

    def rgb_of(rec: Record) -> np.ndarray:
        return pixels.get(rec.image, lambda: load_image(root, rec))

    args.out.mkdir(parents=True, exist_ok=True)
    if detect:

        detector = OnnxDetector(dirs["export"], args.threads)
        # a dataset's calibration goes with its detections: the footprints need the camera
        every = [with_calibration(detector.detect_every(rgb_of(r), r), r)
                 for r in progress(records, len(records), "detector")]
        # every detection down to the detector's score threshold: what AP integrates over (deepword score
        # --detections); the relations see only those at the operating point
        write_records(args.out / DETECTIONS_FILE, every)
        records = [detector.keep_operating_point(r) for r in every]
        # the footprints take vehicles down to the bundle's footprint point, below the operating point
        # (docs/bev.md, "Which detections the footprints take"): their own pass of the relations
        placed = [detector.keep_footprint_point(r) for r in every] if wants_footprints(args, every) else None
    else:
        placed = None
    name = args.method or default_method(dirs, detect)
    if args.method is None:
        why = "the bundle's end-to-end method" if detect else "on the dataset's own boxes"
        print(f"method: {name} ({why})", file=sys.stderr)
    method = build_method(name, dirs, root, args.threads, rgb_of)
    preds = [method.predict(r) for r in progress(records, len(records), f"relations ({name})")]
    if placed is not None and any(len(p.boxes) != len(r.boxes) for p, r in zip(placed, records, strict=True)):
        placed = [method.predict(r) for r in progress(placed, len(placed), f"relations for the footprints ({name})")]
    else:
        placed = None
    return write_predictions(args, dirs, preds, rgb_of, overlays, placed)


def wants_footprints(args, records: list[Record]) -> bool:
    """Whether footprints will be asked for: a calibration given (``--calibration``, ``--rig``) or in the records."""
    return bool(args.calibration) or args.rig is not None or any("calibration" in r.extra for r in records)


def write_predictions(args, dirs: dict[str, Path], preds: list[Record], rgb_of, overlays: int,
                      placed: list[Record] | None = None) -> list[Record]:
    """``labels.jsonl`` with the footprints where there are cameras (``add_footprints``; made from ``placed``, the
    predictions on the footprint point's detections, where given), the first ``overlays`` overlays (each with its
    image's top view), each frame's fused footprints ``footprints.jsonl`` and the top views of frames of several
    images ``top_views/`` beside the overlays."""
    facing_net = OnnxFacing.from_bundle(dirs["export"], args.threads) if "export" in dirs else None
    preds, frames = add_footprints(args, dirs, preds, rgb_of, facing_net, placed)
    if args.roles == "front":
        preds = add_roles(preds, frames, facing_net, rgb_of)
    write_records(args.out / PREDICTIONS_FILE, preds)
    for pred in preds[:overlays]:
        frame = frames.get(pred.frame_id)
        write_overlay(args.out, rgb_of(pred), pred, frame if frame and "objects_3d" in pred.extra else None)
    if frames:  # each frame's fused footprints, as the bev stage writes them; its top view beside the overlays
        write_frame_footprints(args.out, frames)
        write_frame_views(args.out, frames, {p.image for p in preds[:overlays]})
    return preds


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="deepword infer", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("images", nargs="*", type=Path, help="PNG/JPEG images (detector + relation)")
    p.add_argument("--dataset", type=Path, help="a WORD-style dataset root (labels.jsonl) or a data stage output")
    p.add_argument("--detect", action="store_true", help="with --dataset: use detected instead of annotated boxes")
    p.add_argument("--out", type=Path, required=True, help="output folder (labels.jsonl, overlays/)")
    p.add_argument("--method", choices=METHODS, default=None,
                   help="relation method (default: the bundle's end-to-end method on detected boxes, deepword on "
                        "a dataset's own boxes)")
    p.add_argument("--run", help="MLflow run id of the pipeline run whose artifacts to use (default: newest)")
    p.add_argument("--export", type=Path, help="an export stage output directory (instead of --run)")
    p.add_argument("--evaluate", type=Path, help="an evaluate stage output directory (baselines, with --export)")
    p.add_argument("--tracking-uri", help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)")
    p.add_argument("--cache-dir", help="the pipeline's cache directory (default: $DEEPWORD_CACHE or the run's)")
    p.add_argument("--camera", choices=CAMERAS, default="front", help="camera name written for loose images")
    p.add_argument("--overlays", type=int, default=0, help="with --dataset: overlays for the first N images")
    p.add_argument("--threads", type=int, default=1,
                   help="onnxruntime intra-op threads, and processes fitting the footprints of a dataset's frames")
    p.add_argument("--image-memory-mb", type=int, default=DEFAULT_BUDGET_MB,
                   help="decoded images kept in memory between the passes over them, at most this many MiB; beyond it "
                        "an image is decoded again (default: %(default)s)")
    p.add_argument("--calibration", type=Path, nargs="+", help="WoodScape-style calibration JSON of the loose "
                   "images' camera, or one per image in the images' order (footprints in bird's-eye view; a dataset's "
                   "own `calibration` needs no flag)")
    p.add_argument("--frame", action="store_true", help="the loose images are one instant's cameras (one frame): "
                   "each camera named by its calibration file, their footprints fused into top_views/frame_000000.png")
    p.add_argument("--rig", type=Path, help="the loose images are a recorded drive of the rig's cameras: each image's "
                   "camera from a camera-named folder (front/, left/, rear/, right/) or a WoodScape suffix (_FV, _MVL, "
                   "_MVR, _RV), its instant from the number in its name; this folder holds one calibration JSON per "
                   "camera. Each instant's footprints fused into top_views/frame_<n>.png")
    p.add_argument("--bev", type=Path, help="a bev stage output directory (its footprint prior; default: the run's)")
    p.add_argument("--roles", choices=("front", "network"), default="front",
                   help="each wheel's front/rear role: read from which way its vehicle faces (its footprint, else "
                        "the facing network's vector; default), or as the relation network wrote it")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if bool(args.images) == (args.dataset is not None):
        p.error("give either IMAGE... or --dataset ROOT")
    if args.detect and args.dataset is None:
        p.error("--detect goes with --dataset (loose images are always detected)")
    if args.rig is not None and (args.dataset is not None or args.frame or args.calibration):
        p.error("--rig goes with loose images, without --frame or --calibration (it names each image's camera and "
                "frame, and holds the calibrations)")
    if args.frame and args.dataset is not None:
        p.error("--frame goes with loose images (a dataset's records carry their frame_id)")

    try:
        preds = infer(args)
    except (InferError, DatasetError, ResolveError, NoDetectorError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    n_rel = sum(len(r.relations) for r in preds)
    print(f"{len(preds)} images, {n_rel} owner-member relations -> {args.out / PREDICTIONS_FILE}")
    decided = {}
    for r in preds:
        for rule, n in (r.extra.get(ROLES_FROM_KEY) or {}).items():
            decided[rule] = decided.get(rule, 0) + n
    if any(decided.values()):
        print("wheel roles read from: " + ", ".join(f"{rule} {n}" for rule, n in decided.items())
              + " (docs/bev.md, \"The wheels' roles, read back from the front\")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
