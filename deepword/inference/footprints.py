"""Footprints for predictions outside the pipeline (``deepword infer``): frame by frame (the images of one instant
estimated and fused together, the bev stage's ``frame_footprints``), with the footprint prior the bev stage fitted on
train (its shape statistics and heading table, ``footprint_prior.json``) and a calibration from the dataset or a
WoodScape JSON file."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from deepword.cameras import Camera, camera_from_calibration
from deepword.footprint import (
    MIN_CAMERA_PAIRS,
    Estimate,
    FootprintPrior,
    agreement_trust,
    camera_agreement,
    facing_trust,
    footprint_json,
    frame_footprints,
    implied_accuracy,
    record_contacts,
    refuse_weighed,
    write_footprints,
)
from deepword.format_3d import Box3D, check_calibration
from deepword.frame_processes import map_frames
from deepword.top_view import LEGEND_PX, TITLE_PX, fused_top_view
from deepword.word_format import CAMERAS, Record

PRIOR_FILE = "footprint_prior.json"     # the bev stage's fitted prior (shape statistics, heading table)
BEV_REPORT = "bev.json"                 # the bev stage's numbers, with the fusion radius it used
FOOTPRINTS_FILE = "footprints.jsonl"    # infer's fused footprints per frame, as the bev stage's footprints/*.jsonl
DEFAULT_FUSE_RADIUS_M = 1.5             # conf/bev/default.yaml's fuse_radius_m, for a bev output without bev.json's


class CalibrationError(ValueError):
    """A calibration file or footprint prior that cannot be used; the message names the file."""


def load_prior(bev_dir: Path) -> FootprintPrior:
    path = Path(bev_dir) / PRIOR_FILE
    if not path.is_file():
        raise CalibrationError(f"{path}: no footprint prior (the bev stage writes it; was it run on a dataset "
                               "with calibration?)")
    return FootprintPrior.from_json(json.loads(path.read_text()))


def read_calibration_file(path: Path, width: int, height: int) -> dict:
    """A WoodScape-style calibration JSON (intrinsic + extrinsic; extra keys such as ``name`` ignored),
    validated for an image of ``width`` x ``height``."""
    try:
        cal = json.loads(Path(path).read_text())
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot be read: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}:{exc.lineno}: malformed JSON: {exc.msg}") from None

    def fail(field: str, message: str):
        raise CalibrationError(f"{path}: field '{field.removeprefix('calibration.')}': {message}")

    check_calibration(cal, width, height, fail)
    return cal


@dataclass
class Frame:
    """One instant's footprints: its images with their cameras, the frame's fused footprints (the bev stage's
    ``frame_footprints``) and each image's wheel contact points."""

    frame_id: int
    views: list[tuple[Record, Camera]]
    fused: list[tuple[Box3D, list[Estimate]]]
    contacts: dict[str, dict[int, np.ndarray]]   # image -> {wheel box_id: ground contact}, where one is found

    def groups_of(self, image: str) -> list[tuple[Box3D, list[Estimate]]]:
        """The fused footprints one of whose estimates comes from ``image``."""
        return [(box, g) for box, g in self.fused if any(e.image == image for e in g)]


def load_fuse_radius(bev_dir: Path) -> float:
    """The fusion radius the bev stage used (its ``bev.json``), else the configured default."""
    path = Path(bev_dir) / BEV_REPORT
    if path.is_file():
        radius = json.loads(path.read_text()).get("fuse_radius_m")
        if radius is not None:
            return float(radius)
    return DEFAULT_FUSE_RADIUS_M


def estimate_frames(views: list[tuple[Record, Camera]], prior: FootprintPrior,
                    fuse_radius_m: float = DEFAULT_FUSE_RADIUS_M,
                    facing_val_accuracy: float | None = None, progress=None, workers: int = 1) -> dict[int, Frame]:
    """The footprints of every frame among ``views`` [(prediction, camera)], grouped by ``frame_id``: each frame's
    images estimated and fused together (``frame_footprints``, as the bev stage does: neighbours' axes across the
    cameras, headings by the roles' votes and the prior's heading table). With ``facing_val_accuracy`` (the facing
    network's, 0-1) the facing votes are weighed by ``facing_trust`` over all the frames, as the bev stage weighs
    them over a test set. ``progress(items, total)``: wraps the loop over the frames (e.g. ``deepword.progress``'s
    ``progress_lines``). ``workers`` > 1: up to that many spawned processes fit the frames
    (``deepword.frame_processes``: the result is the same for any number)."""
    by_frame: dict[int, list] = {}
    for pred, cam in views:
        by_frame.setdefault(pred.frame_id, []).append((pred, cam))
    fitted = map_frames(partial(_fit_frame, prior=prior, fuse_radius_m=fuse_radius_m), list(by_frame.values()),
                        workers, progress)
    estimated = dict(zip(by_frame, fitted, strict=True))
    if facing_val_accuracy is not None:
        weight = facing_trust([g for _, fused in estimated.values() for g in fused], facing_val_accuracy)
        estimated = refuse_weighed(estimated, weight, fuse_radius_m, prior)
    return {frame_id: Frame(frame_id, fviews, estimated[frame_id][1],
                            {pred.image: record_contacts(pred, cam, prior) for pred, cam in fviews})
            for frame_id, fviews in by_frame.items()}


def _fit_frame(views: list[tuple[Record, Camera]], prior: FootprintPrior, fuse_radius_m: float):
    """One frame's ``frame_footprints`` (a module-level function: what a worker process is handed)."""
    return frame_footprints(views, prior, fuse_radius_m)


def with_objects_3d(pred: Record, frame: Frame) -> Record:
    """The prediction with its frame's footprints as ``objects_3d``: per vehicle box the fused footprint its estimate
    joined (``footprint_json``: box, evidence, the cameras that saw it, confidence, ``heading_from``), per wheel its
    contact point; in the calibration's vehicle frame. Boxes the frame was estimated from that ``pred`` lacks (the
    footprint point's extra detections, numbered after its own) are in footprints.jsonl alone."""
    own = set(pred.box_ids.tolist())
    objs = {str(e.vehicle_box_id): footprint_json(box, g)   # a couple no vehicle box owns: footprints.jsonl alone
            for box, g in frame.groups_of(pred.image) for e in g
            if e.image == pred.image and e.vehicle_box_id is not None and e.vehicle_box_id in own}
    objs.update({str(w): {"contact": [round(float(v), 4) for v in xy]}
                 for w, xy in frame.contacts[pred.image].items() if w in own})
    return replace(pred, extra={**pred.extra, "objects_3d": objs})


def image_contacts(frame: Frame, image: str) -> np.ndarray:
    """(N, 2) the ground contacts of the image's wheels whose contact is found."""
    return np.array(list(frame.contacts[image].values())).reshape(-1, 2)


def facing_check(frames: dict[int, Frame], val_accuracy: float) -> str | None:
    """A line on whether the facing network holds on these frames, from how often two cameras' votes on one vehicle
    agree (``deepword.footprint.camera_agreement``), set beside its val accuracy (0-1), with the weight its votes were
    given for it (``facing_trust``, as ``estimate_frames`` gives it); None where no vehicle was voted on by two cameras
    (single images)."""
    fused = [g for frame in frames.values() for g in frame.fused]
    pairs, agreeing = camera_agreement(fused)
    implied = implied_accuracy(pairs, agreeing)
    if implied is None:
        return None
    line = (f"facing network: two cameras' votes on one vehicle agree for {agreeing} of {pairs} camera pairs, as a "
            f"network right for ~{100 * implied:.0f} % of vehicles would ({100 * val_accuracy:.1f} % on its val split)")
    if pairs < MIN_CAMERA_PAIRS:
        return line + f"; too few pairs to judge (under {MIN_CAMERA_PAIRS})"
    weight = agreement_trust(pairs, agreeing, val_accuracy)
    if weight < 1.0:
        return (line + f"; well below, so its votes counted x {weight:.2f}: its fronts may not hold on these images. "
                "Check a few top views, and where the fronts are wrong run the pipeline with pipeline.skip=[facing] "
                "(docs/bev.md, \"Front and back\")")
    return line


BESIDE_MIN_PX = 320   # the narrowest map beside an overlay: the legend's widest row without truth needs 312 px


def beside_top_view(overlay: np.ndarray, image: str, frame: Frame, half_extent_m: float = 12.0) -> np.ndarray:
    """The overlay with a top view of its image's footprints (as fused over the frame) to its right: title, map and
    legend as tall as the overlay, the map at least ``BESIDE_MIN_PX`` wide (the legend's widest row needs 312 px), the
    shorter of the two padded with white below."""
    h = overlay.shape[0]
    cam = next(c for p, c in frame.views if p.image == image)
    groups = frame.groups_of(image)
    view = fused_top_view([], groups, image_contacts(frame, image), cam.translation[None, :2],
                          f"{len(groups)} footprints, camera {cam.name}", half_extent_m,
                          size_px=max(h - TITLE_PX - LEGEND_PX, BESIDE_MIN_PX))
    height = max(h, view.shape[0])
    return np.concatenate([_white_below(overlay, height), _white_below(view, height)], axis=1)


def _white_below(img: np.ndarray, height: int) -> np.ndarray:
    return np.pad(img, ((0, height - img.shape[0]), (0, 0), (0, 0)), constant_values=255)


def camera_of(pred: Record, calibration: dict | None) -> Camera | None:
    """The prediction's camera: the given calibration, else the record's own, else None."""
    cal = calibration if calibration is not None else pred.extra.get("calibration")
    return None if cal is None else camera_from_calibration(cal, name=pred.camera)


WOODSCAPE_CAMERAS = {"FV": "front", "MVL": "left", "MVR": "right", "RV": "rear"}
FRAME_VIEW_DIR = "top_views"


def calibration_camera(cal: dict, path: Path, default: str) -> str:
    """The camera a calibration file is of: its ``name`` (WoodScape's FV / MVL / MVR / RV, or front / left /
    right / rear), else the file's stem when that names a camera, else ``default``."""

    for name in (str(cal.get("name", "")), Path(path).stem):
        for key in (name, name.upper(), name.lower()):
            if key in WOODSCAPE_CAMERAS:
                return WOODSCAPE_CAMERAS[key]
            if key in CAMERAS:
                return key
    return default


RIG_NAMING = ("a camera-named folder in its path (front/, left/, rear/, right/) or a WoodScape suffix (_FV, _MVL, "
              "_MVR, _RV), and the frame's number in its name (000042.png, 00042_FV.png)")


def rig_view_of(path: Path) -> tuple[str, int] | None:
    """(camera, frame number) of an image of a recorded drive, from its path: the camera from a camera-named folder
    (``front/000042.png``, the importer's convention) or a WoodScape suffix (``00042_FV.png``), the frame from the
    digits of its name; None where either is missing (``RIG_NAMING``)."""
    path = Path(path)
    stem, camera = path.stem, None
    head, _, suffix = stem.rpartition("_")
    if head and suffix.upper() in WOODSCAPE_CAMERAS:
        stem, camera = head, WOODSCAPE_CAMERAS[suffix.upper()]
    camera = camera or next((part for part in reversed(path.parent.parts) if part in CAMERAS), None)
    if camera is None or not stem.isdigit():
        return None
    return camera, int(stem)


def read_rig_calibrations(folder: Path, sizes: dict[str, set[tuple[int, int]]]) -> dict[str, dict]:
    """{camera: calibration} for the cameras of ``sizes`` ({camera: the (width, height) of its images}) from the JSON
    files of ``folder``, one per camera, each named by its ``name`` or its file's stem (``calibration_camera``) and
    validated for its images' size. CalibrationError where a camera's images differ in size, or naming the folder or
    file where a camera has no calibration, or two."""
    for camera, found in sizes.items():
        if len(found) > 1:
            raise CalibrationError(f"the {camera} camera's images have {len(found)} different sizes "
                                   f"({', '.join(f'{w}x{h}' for w, h in sorted(found))}): one calibration cannot fit "
                                   "them")
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: not a folder (the rig's calibrations: one JSON file per camera)")
    found: dict[str, Path] = {}
    for path in sorted(folder.glob("*.json")):
        try:
            cal = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"{path}: not JSON ({exc})") from None
        camera = calibration_camera(cal if isinstance(cal, dict) else {}, path, "")
        if camera in found:
            raise CalibrationError(f"{folder}: two calibrations of the {camera} camera ({found[camera].name}, "
                                   f"{path.name})")
        if camera:
            found[camera] = path
    out = {}
    for camera, ((width, height),) in sorted(sizes.items()):
        if camera not in found:
            raise CalibrationError(f"{folder}: no calibration of the {camera} camera (a JSON file named {camera}.json "
                                   f"or {next(k for k, v in WOODSCAPE_CAMERAS.items() if v == camera)}.json, or with "
                                   f"that \"name\")")
        out[camera] = read_calibration_file(found[camera], width, height)
    return out


def frame_top_view(frame: Frame, title: str, half_extent_m: float = 14.0, size_px: int = 420) -> np.ndarray:
    """One instant's top view: the frame's fused footprints around the rig of all its cameras, coloured by the camera
    whose estimate leads each, an arrow to the front where the wheels' roles voted."""
    rig = np.array([cam.translation[:2] for _, cam in frame.views])
    contacts = [image_contacts(frame, p.image) for p, _ in frame.views]
    fused = frame.fused
    return fused_top_view([], fused, np.concatenate(contacts) if contacts else np.zeros((0, 2)), rig,
                          f"{title}: {len(fused)} vehicles, {len(frame.views)} cameras", half_extent_m, size_px)


def write_frame_views(out_dir: Path, frames: dict[int, Frame], shown: set[str] | None = None) -> list[Path]:
    """``out_dir/top_views/frame_<id>.png`` for every frame of two or more images (a single image's top view is
    beside its overlay already) one of whose images is in ``shown`` (every frame when None)."""
    import cv2

    paths = []
    for frame_id, frame in sorted(frames.items()):
        if len(frame.views) < 2 or (shown is not None and not any(p.image in shown for p, _ in frame.views)):
            continue
        path = Path(out_dir) / FRAME_VIEW_DIR / f"frame_{frame_id:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), cv2.cvtColor(frame_top_view(frame, f"frame {frame_id}"), cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths


def write_frame_footprints(out_dir: Path, frames: dict[int, Frame]) -> Path:
    """``out_dir/footprints.jsonl``: each frame's fused footprints, as the bev stage writes ``footprints/*.jsonl``."""
    path = Path(out_dir) / FOOTPRINTS_FILE
    write_footprints(path, {f: frame.fused for f, frame in frames.items()})
    return path
