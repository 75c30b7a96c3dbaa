"""The Kannala-Brandt projection: cv2.fisheye inside its valid range, beyond 90 deg, behind, round trip."""

import cv2
import numpy as np
import pytest

from stages.data.camera import camera_from_config
from tests.stages.data.data_helpers import synword_cfg


@pytest.fixture(params=["front", "left", "right", "rear"])
def cam(request):
    cfg = synword_cfg()
    return camera_from_config(request.param, cfg["cameras"][request.param], 640, 480,
                              cfg["cameras"]["reference_size"])


def _cv2_project(cam, pts_cam):
    uv, _ = cv2.fisheye.projectPoints(pts_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.D)
    return uv.reshape(-1, 2)


def test_matches_cv2_fisheye_in_front_of_the_camera(cam):
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, np.radians(85), 500)
    phi = rng.uniform(-np.pi, np.pi, 500)
    dist = rng.uniform(0.5, 30, 500)
    pts = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1) * dist[:, None]
    np.testing.assert_allclose(cam.project_cam(pts), _cv2_project(cam, pts), atol=1e-6)


def test_beyond_90_degrees_lands_in_the_image_on_the_right_side(cam):
    # 93 deg off-axis to the camera's right (+x): cv2's atan(r/z) would mirror it to the left
    theta = np.radians(93)
    pt = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    u, v = cam.project_cam(pt)[0]
    assert cam.K[0, 2] < u < cam.width
    assert abs(v - cam.K[1, 2]) < 1e-6
    mirrored = _cv2_project(cam, pt)[0]
    assert mirrored[0] < cam.K[0, 2]  # documents the pitfall our projection avoids


def test_behind_the_camera_is_out_of_view_not_mirrored(cam):
    behind_right = cam.position + 5 * (-cam.forward + 0.3 * cam.R[0])
    uv, in_fov = cam.project(behind_right[None])
    assert not in_fov[0]
    radius = np.hypot(uv[0, 0] - cam.K[0, 2], uv[0, 1] - cam.K[1, 2])
    assert radius > cam.K[0, 0] * cam.distort(np.array(cam.theta_max))  # outside the image circle
    assert uv[0, 0] > cam.K[0, 2]  # still on its own side


def test_unproject_round_trip(cam):
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [cam.width, cam.height], (400, 2))
    rays, theta = cam.unproject(uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(cam.project_cam(rays * 7.0), uv, atol=1e-6)


def test_pixel_rays_point_where_the_pixels_are(cam):
    rays, valid = cam.pixel_rays()
    assert valid[cam.height // 2, cam.width // 2] and not valid[0, 0]  # black corners of a fisheye
    ys, xs = np.nonzero(valid)
    pick = np.arange(0, len(ys), 997)
    pts = cam.position + 3.0 * rays[ys[pick], xs[pick]].astype(np.float64)
    uv, in_fov = cam.project(pts)
    assert in_fov.all()
    np.testing.assert_allclose(uv, np.stack([xs[pick] + 0.5, ys[pick] + 0.5], 1), atol=1e-3)
