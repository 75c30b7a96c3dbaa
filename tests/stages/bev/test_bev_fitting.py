"""The bev stage's footprint fitting: a silhouette's box is the bbox of its projected edge points, and spreading the
frames over worker processes changes no footprint."""

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


def test_silhouette_boxes_are_the_bbox_of_each_vehicles_projected_points():
    cam = _camera()
    rng = np.random.default_rng(0)
    xy = rng.uniform(-6, 6, (40, 2)) + [0.0, 6.0]
    yaw = rng.uniform(-math.pi, math.pi, 40)
    size = _size(PRIOR, 1.3)
    boxes = silhouette_boxes(cam, xy, yaw, size, PRIOR.shape)
    coef, off = PRIOR.shape.points()
    for i in range(len(xy)):
        local = coef * size + off
        c, s = math.cos(yaw[i]), math.sin(yaw[i])
        world = np.stack([xy[i, 0] + c * local[:, 0] - s * local[:, 1],
                          xy[i, 1] + s * local[:, 0] + c * local[:, 1], local[:, 2]], axis=1)
        pc = cam.to_cam(world)
        chi = np.hypot(pc[:, 0], pc[:, 1])
        out = np.arctan2(chi, pc[:, 2]) > cam.theta_max
        pc[out] = np.c_[pc[out, :2] * (math.sin(cam.theta_max) / chi[out, None]),
                        np.full(out.sum(), math.cos(cam.theta_max))]
        uv = cam.project_cam(pc) - BOX_TO_IMAGE
        want = np.clip(np.r_[uv.min(0), uv.max(0)], 0.0, [cam.width, cam.height, cam.width, cam.height])
        np.testing.assert_allclose(boxes[i], want, rtol=0, atol=1e-9)
    assert (boxes[:, 2] > boxes[:, 0]).any()


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
    two, _ = fused_footprints(jobs, frames, PRIOR, 1.5, workers=2, min_frames_per_process=1)
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
