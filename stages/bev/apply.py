"""Footprints for predictions outside the pipeline (``deepword infer``): one image at a time, with the
footprint prior the bev stage fitted on train and a calibration from the dataset or a WoodScape JSON file."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from stages.bev.figure import top_view
from stages.bev.footprint import FootprintPrior, estimate_record, wheel_contacts
from stages.cameras import Camera, camera_from_calibration
from stages.format_3d import check_calibration
from stages.word_format import WHEEL, Record

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
