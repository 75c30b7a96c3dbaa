"""The bev stage's footprint fitting: a silhouette's box is the bbox of its projected edge points within the field
of view, and spreading the frames over worker processes changes no footprint."""

import math
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from deepword.cameras import BOX_TO_IMAGE
from deepword.footprint import _size, silhouette_boxes
from deepword.format_3d import record_camera
from deepword.word_format import read_records, write_records
from stages.bev.fitting import frame_views, fused_footprints
from stages.data.synword import generate
from tests.stages.bev.test_bev import PRIOR, _camera

CONF = Path(__file__).resolve().parents[3] / "conf"


def _world_points(shape_points, size, xy, yaw):
    coef, off = shape_points
    local = coef * size + off
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack([xy[0] + c * local[:, 0] - s * local[:, 1], xy[1] + s * local[:, 0] + c * local[:, 1],
                     local[:, 2]], axis=1)


def _dense_shape_points(steps: int):
    """The silhouette's edge points at ``steps`` points an edge instead of ``_EDGE_STEPS``'s five."""
    import deepword.footprint as footprint
    kept = footprint._EDGE_STEPS
    try:
        footprint._EDGE_STEPS = tuple(np.linspace(0.0, 1.0, steps))
        return footprint._shape_points.__wrapped__(PRIOR.shape)
    finally:
        footprint._EDGE_STEPS = kept


def test_silhouette_boxes_are_the_bbox_of_each_vehicles_projected_points_within_the_field_of_view():
    """Whole vehicles: the bbox of the projected edge points. Vehicles the image circle cuts: the bbox of what is
    inside it, where a dense sampling of the edges (400 points an edge) puts it, within the curvature that five
    points an edge miss; radially moving the points beyond the border onto it (the old model) missed it by up to
    hundreds of pixels. Vehicles wholly beyond it: their points moved onto the border."""
    cam = _camera()
    rng = np.random.default_rng(0)
    # around the camera, 3-9 m off (a closer vehicle would stand where the ego does)
    bearing, reach = rng.uniform(-math.pi, math.pi, 300), rng.uniform(3.0, 9.0, 300)
    xy = cam.translation[:2] + reach[:, None] * np.c_[np.cos(bearing), np.sin(bearing)]
    yaw = rng.uniform(-math.pi, math.pi, 300)
    size = _size(PRIOR, 1.3)
    boxes = silhouette_boxes(cam, xy, yaw, size, PRIOR.shape)
    dense = _dense_shape_points(401)
    limits = [cam.width, cam.height, cam.width, cam.height]
    kinds = {"whole": 0, "cut": 0, "beyond": 0}
    for i in range(len(xy)):
        pc = cam.to_cam(_world_points(PRIOR.shape.points(), size, xy[i], yaw[i]))
        chi = np.hypot(pc[:, 0], pc[:, 1])
        inside = np.arctan2(chi, pc[:, 2]) <= cam.theta_max
        if inside.all():
            kinds["whole"] += 1
            uv = cam.project_cam(pc) - BOX_TO_IMAGE
            want = np.clip(np.r_[uv.min(0), uv.max(0)], 0.0, limits)
            np.testing.assert_allclose(boxes[i], want, rtol=0, atol=1e-9)
            continue
        pd = cam.to_cam(_world_points(dense, size, xy[i], yaw[i]))
        seen = np.arctan2(np.hypot(pd[:, 0], pd[:, 1]), pd[:, 2]) <= cam.theta_max
        if seen.any():
            kinds["cut"] += 1
            uv = cam.project_cam(pd[seen]) - BOX_TO_IMAGE
            want = np.clip(np.r_[uv.min(0), uv.max(0)], 0.0, limits)
            np.testing.assert_allclose(boxes[i], want, rtol=0, atol=4.0)
        elif not inside.any():
            kinds["beyond"] += 1
            out = ~inside
            pc[out] = np.c_[pc[out, :2] * (math.sin(cam.theta_max) / chi[out, None]),
                            np.full(out.sum(), math.cos(cam.theta_max))]
            uv = cam.project_cam(pc) - BOX_TO_IMAGE
            np.testing.assert_allclose(boxes[i], np.clip(np.r_[uv.min(0), uv.max(0)], 0.0, limits), rtol=0, atol=1e-9)
    assert min(kinds.values()) >= 10, kinds


def test_footprints_are_the_same_for_any_number_of_worker_processes(tmp_path, capsys):
    cfg = {**OmegaConf.to_container(OmegaConf.load(CONF / "data" / "synword.yaml"), resolve=True), "frames": 3,
           "workers": 1}
    write_records(tmp_path / "labels.jsonl", generate(cfg, seed=5, out_dir=tmp_path, workers=1, progress=False))
    test = read_records(tmp_path / "labels.jsonl")
    cameras = {r.image: record_camera(r, "test") for r in test}
    preds = {r.image: r for r in test}
    jobs = {("gt", "deepword"): (frame_views(preds, test, cameras), True),
            ("gt", "box_bottom"): (frame_views(preds, test, cameras), False),
            ("gt", "nothing"): ({}, True)}
    frames = [2, 0, 1, 7]   # 7: a frame no view falls in
    one, trust = fused_footprints(jobs, frames, PRIOR, 1.5, workers=1)
    assert trust == {}   # no facing network: no weights
    two, _ = fused_footprints(jobs, frames, PRIOR, 1.5, workers=2, frames_per_task=1)
    assert "(2 processes)" in capsys.readouterr().out
    assert list(one) == list(jobs) and all(list(fused) == frames for fused in one.values())
    assert sum(len(f) for f in one[("gt", "deepword")].values()) >= 5
    assert one[("gt", "nothing")] == {f: [] for f in frames} and one[("gt", "deepword")][7] == []
    for key in jobs:
        for f in frames:
            assert [(box, [e.box for e in group]) for box, group in two[key][f]] == \
                   [(box, [e.box for e in group]) for box, group in one[key][f]], (key, f)


def test_too_few_frames_for_a_process_each_are_fitted_in_this_one(capsys):
    assert fused_footprints({("gt", "nothing"): ({}, True)}, list(range(15)), PRIOR, 1.5, workers=2)[0] == \
        {("gt", "nothing"): {f: [] for f in range(15)}}
    assert "(1 process)" in capsys.readouterr().out
