"""Footprints for predictions outside the pipeline (``deepword infer``): one image at a time, with the
footprint prior the bev stage fitted on train and a calibration from the dataset or a WoodScape JSON file."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from deepword.cameras import Camera, camera_from_calibration
from deepword.footprint import FootprintPrior, estimate_record, fuse_frame, group_directed, wheel_contacts
from deepword.format_3d import check_calibration
from deepword.top_view import top_view
from deepword.word_format import CAMERAS, WHEEL, Record

PRIOR_FILE = "footprint_prior.json"


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


def footprints(pred: Record, cam: Camera, prior: FootprintPrior) -> tuple[Record, list, np.ndarray]:
    """(the prediction with its estimated footprints as ``objects_3d``, the estimates, the wheels' contact
    points). The footprints are in the calibration's vehicle frame; ``evidence`` says what each rests on."""
    estimates = estimate_record(pred, cam, prior)
    wheels = pred.boxes[pred.class_ids == WHEEL]
    contacts = np.zeros((0, 2))
    objs = {str(e.vehicle_box_id): {**e.box.to_json(), "evidence": e.evidence} for e in estimates}
    if len(wheels):
        xy, ok = wheel_contacts(cam, wheels[:, :4], prior)
        contacts = xy[ok]
        objs.update({str(int(w[6])): {"contact": [round(float(v), 4) for v in xy[i]]}
                     for i, w in enumerate(wheels) if ok[i]})
    return replace(pred, extra={**pred.extra, "objects_3d": objs}), estimates, contacts


def beside_top_view(overlay: np.ndarray, cam: Camera, estimates: list, contacts: np.ndarray,
                    half_extent_m: float = 12.0) -> np.ndarray:
    """The overlay with a top view of the image's footprints to its right, as tall as the overlay."""
    h = overlay.shape[0]
    view = top_view([], [e.box for e in estimates], contacts, cam.translation[None, :2],
                    f"{len(estimates)} footprints, camera {cam.name}", half_extent_m, size_px=max(h - 24, 64))
    if view.shape[0] != h:
        pad = np.full((h, view.shape[1], 3), 255, np.uint8)
        pad[: min(h, view.shape[0])] = view[:h]
        view = pad
    return np.concatenate([overlay, view], axis=1)


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


def frame_top_view(views: list, title: str, half_extent_m: float = 14.0, fuse_radius_m: float = 1.5,
                   size_px: int = 420) -> np.ndarray:
    """One instant's top view: the footprints of its images ``views`` [(camera, estimates, contacts)] fused as the
    bev stage fuses a frame's cameras (``fuse_frame``), around the rig of all their cameras, coloured by camera."""

    fused = fuse_frame([e for _, estimates, _ in views for e in estimates], fuse_radius_m)
    rig = np.array([cam.translation[:2] for cam, _, _ in views])
    contacts = [c for _, _, c in views if len(c)]
    return top_view([], [b for b, _ in fused], np.concatenate(contacts) if contacts else np.zeros((0, 2)), rig,
                    f"{title}: {len(fused)} vehicles, {len(views)} cameras", half_extent_m, size_px,
                    cameras=[g[0].camera for _, g in fused], directed=[group_directed(g) for _, g in fused],
                    seen_by=[len({e.camera for e in g}) for _, g in fused])


def write_frame_views(out_dir: Path, preds: list[Record], views: dict) -> list[Path]:
    """``out_dir/top_views/frame_<id>.png`` for every frame of ``preds`` with footprints from two or more images
    (a single image's top view is beside its overlay already)."""
    import cv2

    by_frame: dict[int, list] = {}
    for pred in preds:
        if pred.image in views:
            by_frame.setdefault(pred.frame_id, []).append(views[pred.image])
    paths = []
    for frame, frame_views in sorted(by_frame.items()):
        if len(frame_views) < 2:
            continue
        path = Path(out_dir) / FRAME_VIEW_DIR / f"frame_{frame:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), cv2.cvtColor(frame_top_view(frame_views, f"frame {frame}"), cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths
