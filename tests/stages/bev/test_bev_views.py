"""Top views: the bev stage's per-frame figure panels (legend, cameras' colours) and ``deepword infer``'s fused
top view of one instant's cameras (several calibration files, one per image)."""

import argparse
import math

import numpy as np
import pytest

from deepword.footprint import footprints_from_contacts, fuse_frame
from deepword.format_3d import Box3D
from deepword.inference.footprints import Frame, calibration_camera, frame_top_view, write_frame_views
from deepword.top_view import CAMERA_RGB, FULL_CONFIDENCE, LEGEND_PX, TITLE_PX, TRUE_RGB, faded, top_view
from stages.data.camera import nominal_camera
from stages.inference.infer import InferError, add_footprints, parser
from tests.stages.bev.test_bev import LEFT, PRIOR, _camera, _contacts, _record


def _has(img, rgb) -> bool:
    return bool((np.abs(img.astype(int) - np.array(rgb)).sum(axis=2) <= 30).any())   # anti-aliased lines


def _frame_views():
    v = Box3D(8.0, 2.6, 4.5, 1.8, 0.05)
    c = _contacts(v)
    left = _camera()
    front = nominal_camera("front", {**LEFT, "yaw_deg": 0.0, "pitch_deg": 23.0, "position": [3.7, 0.0, 0.66]},
                           640, 480, [640, 480])
    r_left = _record(left, [(0, 1, "rear"), (0, 2, "front")], [(1, 2)], n_vehicles=1, n_wheels=2)
    r_front = _record(front, [(0, 1, "rear"), (0, 2, "rear")], [], n_vehicles=1, n_wheels=2, camera="front",
                      image="images/front/000000.png")
    views = {r_left.image: (left, footprints_from_contacts(r_left, left, PRIOR, {1: c["rr"], 2: c["fr"]}),
                            np.array([c["rr"], c["fr"]])),
             r_front.image: (front, footprints_from_contacts(r_front, front, PRIOR, {1: c["rl"], 2: c["rr"]}),
                             np.array([c["rl"], c["rr"]]))}
    return v, [r_left, r_front], views


def _frame(recs, views) -> Frame:
    """The frame of ``recs`` as ``deepword infer`` holds it: their cameras, the fused estimates, the contacts."""
    return Frame(0, [(r, views[r.image][0]) for r in recs],
                 fuse_frame([e for r in recs for e in views[r.image][1]], 1.5, PRIOR),
                 {r.image: dict(zip(r.boxes[r.class_ids == 1][:, 6].astype(int).tolist(), views[r.image][2], strict=True))
                  for r in recs})


def test_a_panel_has_truth_the_cameras_colours_and_a_legend():
    v, _, views = _frame_views()
    (cam, estimates, contacts) = views["images/left/000000.png"]
    img = top_view([v], [e.box for e in estimates], contacts, np.array([[0.0, 0.0], [3.7, 0.0]]), "t",
                   cameras=["left"], directed=[True], seen_by=[1])
    assert img.shape == (TITLE_PX + 420 + LEGEND_PX, 420, 3)
    assert _has(img, TRUE_RGB) and _has(img[: TITLE_PX + 420], CAMERA_RGB["left"])
    assert not _has(img[: TITLE_PX + 420], CAMERA_RGB["right"])   # no right-camera estimate drawn above the legend


def test_a_low_confidence_footprint_is_drawn_pale():
    v, _, views = _frame_views()
    (cam, estimates, contacts) = views["images/left/000000.png"]
    rig, view = np.array([[0.0, 0.0], [3.7, 0.0]]), slice(0, TITLE_PX + 420)

    def drawn(confidence):
        return top_view([], [e.box for e in estimates], contacts, rig, "t", cameras=["left"], directed=[True],
                        seen_by=[1], confidence=confidence)[view]

    assert _has(drawn([0.9]), CAMERA_RGB["left"]) and _has(drawn(None), CAMERA_RGB["left"])
    pale = drawn([0.01])
    assert not _has(pale, CAMERA_RGB["left"]) and _has(pale, faded(CAMERA_RGB["left"], 0.01))
    assert faded((0, 0, 0), 0.0) == (178, 178, 178) and faded((10, 20, 30), FULL_CONFIDENCE) == (10, 20, 30)


def test_one_instants_cameras_fuse_into_one_top_view(tmp_path):
    v, recs, views = _frame_views()
    frame = _frame(recs, views)
    assert len(frame.fused) == 1 and len(frame.fused[0][1]) == 2   # the two cameras' estimates: one vehicle
    img = frame_top_view(frame, "frame 0")
    assert _has(img[: TITLE_PX + 420], CAMERA_RGB["left"])   # the left camera's side estimate leads the fused vehicle
    paths = write_frame_views(tmp_path, {0: frame})
    assert [p.name for p in paths] == ["frame_000000.png"] and paths[0].is_file()
    # a frame seen by one image only gets no fused view (its overlay carries its top view), nor one none of whose
    # images is overlaid
    assert write_frame_views(tmp_path / "one", {0: _frame(recs[:1], views)}) == []
    assert write_frame_views(tmp_path / "none", {0: frame}, shown={"images/other.png"}) == []


def test_calibration_files_name_their_cameras_and_must_be_one_per_image(tmp_path):
    assert calibration_camera({"name": "MVL"}, tmp_path / "x.json", "front") == "left"
    assert calibration_camera({}, tmp_path / "rear.json", "front") == "rear"
    assert calibration_camera({"name": "other"}, tmp_path / "x.json", "front") == "front"
    args = parser().parse_args(["a.png", "b.png", "--out", str(tmp_path), "--frame",
                                "--calibration", "f.json", "l.json", "r.json"])
    assert args.frame and len(args.calibration) == 3
    _, recs, _ = _frame_views()
    with pytest.raises(InferError, match="3 files for 2 images"):
        add_footprints(args, {}, recs, None, None)
    assert isinstance(args, argparse.Namespace) and math.isfinite(PRIOR.width)


def test_panels_are_laid_out_in_rows_of_four_padded_with_white():
    import numpy as np

    from deepword.top_view import panel_grid

    panels = [np.full((10, 20, 3), i, np.uint8) for i in range(7)]
    grid = panel_grid(panels)
    assert grid.shape == (20, 80, 3)
    assert (grid[10:, 60:] == 255).all() and (grid[10:, 40:60] == 6).all() and (grid[:10, :20] == 0).all()
    assert panel_grid(panels[:3]).shape == (10, 60, 3)   # one row: no padding
