"""BEV footprints from wheel contacts: exact on a hand-built scene, moved by a wrong relation, fused over
cameras, honest about missing calibration, and close to the truth on rendered SynWORD frames."""

import math

import numpy as np
import pytest

from deepword.footprint import (
    MIN_SLOPE_WHEELS,
    FootprintPrior,
    estimate_record,
    fit_contact_shift,
    fit_prior,
    footprints_from_contacts,
    fuse_frame,
    wheel_contacts,
)
from deepword.format_3d import Box3D, Missing3DError, record_camera, record_objects_3d
from deepword.word_format import Record, read_records, write_records
from stages.bev.metrics import TrueVehicle, match_frame, summarise
from stages.bev.stage import check_3d
from stages.data.camera import nominal_camera

LEFT = {"K": {"fx": 184.0, "fy": 184.0, "cx": 319.0, "cy": 239.5}, "D": [0.021, -0.0031, 0.0003, -0.00001],
        "fov_deg": 190, "position": [0.85, 1.05, 1.0], "yaw_deg": 90.0, "pitch_deg": 38.0}
INSET = 0.12
PRIOR = FootprintPrior(width=1.8, length=4.5, wheelbase=2.7, length_slope=1.0, length_offset=1.8, track_inset=INSET,
                       contact_shift=0.0, box_shift=0.0)


def _camera(yaw=90.0, position=(0.85, 1.05, 1.0)):
    return nominal_camera("left", {**LEFT, "yaw_deg": yaw, "position": list(position)}, 640, 480, [640, 480])


def _contacts(v: Box3D, wheelbase: float = 2.7) -> dict[str, np.ndarray]:
    """Contacts of a vehicle with equal overhangs: rear/front x left/right."""
    u, n = np.array([math.cos(v.yaw), math.sin(v.yaw)]), np.array([-math.sin(v.yaw), math.cos(v.yaw)])
    c = np.array([v.x, v.y])
    side = v.width / 2 - INSET
    return {"rl": c - u * wheelbase / 2 + n * side, "fl": c + u * wheelbase / 2 + n * side,
            "rr": c - u * wheelbase / 2 - n * side, "fr": c + u * wheelbase / 2 - n * side}


def _record(cam, relations, pairs, n_vehicles=2, n_wheels=4, camera="left", image="images/left/000000.png"):
    boxes = [[100.0 + 10 * i, 100.0, 150.0 + 10 * i, 160.0, 1.0, 0, i] for i in range(n_vehicles)]
    boxes += [[200.0 + 5 * k, 200.0, 210.0 + 5 * k, 212.0, 1.0, 1, n_vehicles + k] for k in range(n_wheels)]
    return Record(image=image, frame_id=0, camera=camera, width=cam.width, height=cam.height,
                  boxes=np.array(boxes), relations=relations, wheel_pairs=pairs)


def test_hand_built_scene_gives_the_true_footprint_and_zero_error():
    cam = _camera()
    a = Box3D(-1.2, 4.6, 4.5, 1.8, 0.08)
    b = Box3D(4.0, 5.0, 4.5, 1.8, -0.05)
    ca, cb = _contacts(a), _contacts(b)
    # the left camera sees both cars' right sides: vehicle 0 = a, 1 = b; wheels 2, 3 of a; 4, 5 of b
    rec = _record(cam, [(0, 2, None), (0, 3, None), (1, 4, None), (1, 5, None)], [(2, 3), (4, 5)])
    contacts = {2: ca["rr"], 3: ca["fr"], 4: cb["rr"], 5: cb["fr"]}
    est = footprints_from_contacts(rec, cam, PRIOR, contacts)
    assert [e.evidence for e in est] == ["side", "side"]
    for e, truth in zip(est, (a, b), strict=True):
        np.testing.assert_allclose(e.box.corners(), truth.corners(), atol=1e-9)
    summary = summarise(match_frame([TrueVehicle(a), TrueVehicle(b)], [e.box for e in est], 2.0))
    assert summary["center_err_m"] == pytest.approx(0, abs=1e-9) and summary["heading_err_deg"] == pytest.approx(0, abs=1e-6)
    assert summary["corner_err_m"] == pytest.approx(0, abs=1e-9) and summary["bev_iou"] == pytest.approx(1.0)
    assert summary["recall"] == 100.0

    # a wrong relation (logic's classic error: a's front wheel given to b, b's rear wheel to a) moves both
    wrong = _record(cam, [(0, 2, None), (1, 3, None), (0, 4, None), (1, 5, None)], [(2, 4), (3, 5)])
    bad = footprints_from_contacts(wrong, cam, PRIOR, contacts)
    moved = summarise(match_frame([TrueVehicle(a), TrueVehicle(b)], [e.box for e in bad], 2.0))
    assert math.hypot(bad[0].box.x - a.x, bad[0].box.y - a.y) > 1.0
    assert moved["recall"] < 100 or moved["center_err_m"] > 0.5
    assert moved["bev_iou"] < 0.6 or moved["recall"] < 100


def test_two_cameras_seeing_one_vehicle_give_one_footprint():
    v = Box3D(8.0, 2.6, 4.5, 1.8, 0.05)
    c = _contacts(v)
    left = _camera()
    front = nominal_camera("front", {**LEFT, "yaw_deg": 0.0, "pitch_deg": 23.0, "position": [3.7, 0.0, 0.66]},
                           640, 480, [640, 480])
    # the left camera sees the right side, the front camera the rear axle of the same car
    r_left = _record(left, [(0, 1, None), (0, 2, None)], [(1, 2)], n_vehicles=1, n_wheels=2)
    r_front = _record(front, [(0, 1, None), (0, 2, None)], [], n_vehicles=1, n_wheels=2, camera="front",
                      image="images/front/000000.png")
    est = footprints_from_contacts(r_left, left, PRIOR, {1: c["rr"], 2: c["fr"]})
    est += footprints_from_contacts(r_front, front, PRIOR, {1: c["rl"], 2: c["rr"]})
    assert sorted(e.evidence for e in est) == ["axle", "side"]
    fused = fuse_frame(est, radius_m=1.5)
    assert len(fused) == 1 and len(fused[0][1]) == 2
    box, group = fused[0]
    assert group[0].evidence == "side" and math.hypot(box.x - v.x, box.y - v.y) < 1e-9
    # a second car 2.5 m away stays a car of its own
    other = _record(left, [(0, 1, None), (0, 2, None)], [(1, 2)], n_vehicles=1, n_wheels=2)
    c2 = _contacts(Box3D(v.x, v.y + 2.5, 4.5, 1.8, 0.05))
    est += footprints_from_contacts(other, left, PRIOR, {1: c2["rr"], 2: c2["fr"]})
    assert len(fuse_frame(est, radius_m=1.5)) == 2


def test_the_contact_shift_is_fitted_as_a_median_line_over_distance():
    rng = np.random.default_rng(0)
    distance = rng.uniform(1.0, 20.0, 400)
    shift = 0.09 + 0.03 * distance + rng.normal(0.0, 0.05, 400)
    shift[:40] += 3.0                                   # a tenth of the boxes badly drawn: the median line ignores them
    intercept, slope = fit_contact_shift(list(zip(distance, shift, strict=True)))
    assert intercept == pytest.approx(0.09, abs=0.03) and slope == pytest.approx(0.03, abs=0.003)
    few = [(d, 0.3) for d in np.linspace(1.0, 20.0, MIN_SLOPE_WHEELS - 1)]
    assert fit_contact_shift(few) == (0.3, 0.0)        # too few wheels for a line: the median alone
    assert fit_contact_shift([]) == (0.0, 0.0)


def test_wheel_contacts_move_away_from_the_camera_by_the_shift_at_their_distance():
    cam = _camera()
    boxes = np.array([[300.0, 300.0, 320.0, 330.0], [310.0, 250.0, 318.0, 262.0]])   # a near and a farther wheel
    plain, ok = wheel_contacts(cam, boxes, None)
    assert ok.all()
    prior = FootprintPrior(**{**PRIOR.__dict__, "contact_shift": 0.1, "contact_slope": 0.03})
    moved, _ = wheel_contacts(cam, boxes, prior)
    distance = np.linalg.norm(plain - cam.translation[:2], axis=1)
    np.testing.assert_allclose(np.linalg.norm(moved - cam.translation[:2], axis=1), distance + 0.1 + 0.03 * distance)
    assert distance[1] > distance[0] + 0.5


def test_records_without_calibration_are_named_by_file_and_line(tmp_path):
    cam = _camera()
    base = _record(cam, [(0, 2, None)], [], n_vehicles=2, n_wheels=1)
    with_3d = Record(**{**base.__dict__, "extra": {"calibration": cam.calibration(),
                                                  "objects_3d": {"0": Box3D(1, 4, 4.5, 1.8, 0, 1.5).to_json()}}})
    without = Record(**{**base.__dict__, "image": "images/left/000001.png", "frame_id": 1})
    write_records(tmp_path / "labels.jsonl", [with_3d, without])
    records = read_records(tmp_path / "labels.jsonl")
    with pytest.raises(Missing3DError, match=r"labels.jsonl:2: field 'calibration': missing"):
        check_3d(records)
    assert check_3d([records[1]]) is False   # a plain 2D dataset: nothing to do, no error
    assert check_3d([records[0]]) is True
    with pytest.raises(Missing3DError, match="labels.jsonl:2: field 'objects_3d'"):
        record_objects_3d(records[1], "the bev stage")


def test_rendered_frames_give_footprints_near_the_truth(tmp_path):
    from pathlib import Path

    from omegaconf import OmegaConf

    from stages.data.synword import generate

    conf = Path(__file__).resolve().parents[3] / "conf" / "data" / "synword.yaml"
    cfg = {**OmegaConf.to_container(OmegaConf.load(conf), resolve=True), "frames": 6, "workers": 1}
    records = generate(cfg, seed=3, out_dir=tmp_path, workers=1, progress=False)
    write_records(tmp_path / "labels.jsonl", records)
    records = read_records(tmp_path / "labels.jsonl")  # through the reader: calibration validated
    samples = [(r, record_camera(r, "test"), *record_objects_3d(r, "test")) for r in records]
    prior = fit_prior(samples)
    assert 1.6 < prior.width < 2.1 and 2.2 < prior.wheelbase < 3.6 and abs(prior.contact_shift) < 0.5
    errors, box_errors = [], []
    for rec, cam, vehicles, _ in samples:
        owner = rec.owner_of()
        paired = {owner[a] for a, b in rec.wheel_pairs}
        for rel, errs in ((True, errors), (False, box_errors)):
            for e in estimate_record(rec, cam, prior, use_relations=rel):
                t = vehicles[e.vehicle_box_id]
                if e.vehicle_box_id in paired and math.hypot(t.x, t.y) < 10:
                    errs.append(math.hypot(e.box.x - t.x, e.box.y - t.y))
    assert len(errors) >= 10
    # measured 0.12 m against 1.31 m for box_bottom (seed 3)
    assert np.median(errors) < 0.3 and 2 * np.median(errors) < np.median(box_errors)


def test_the_detected_top_view_shows_the_method_evaluate_headlined(tmp_path):
    """The bev stage draws the end-to-end method evaluate recorded, DeepWORD for an evaluate output without one."""
    import json

    from stages.bev.stage import end_to_end_method

    assert end_to_end_method(tmp_path / "report.json") == "deepword"
    (tmp_path / "report.json").write_text(json.dumps({"results": {}}))
    assert end_to_end_method(tmp_path / "report.json") == "deepword"
    (tmp_path / "report.json").write_text(json.dumps({"results": {}, "end_to_end": "deepword_then_logic"}))
    assert end_to_end_method(tmp_path / "report.json") == "deepword_then_logic"
