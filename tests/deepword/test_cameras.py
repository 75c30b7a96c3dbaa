"""Camera models (deepword.cameras): round trips for both lens models including rays beyond 90 deg off-axis,
agreement with cv2.fisheye inside its valid range, WoodScape's published convention, ground back-projection."""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from deepword.cameras import (
    camera_from_calibration,
    ego_body_outline,
    matrix_to_quaternion,
    mount_rotation,
    quaternion_to_matrix,
)
from deepword.format_3d import check_ego_body
from stages.data.camera import sample_intrinsic

LENS_CFG = {"fov_deg": [170, 200], "edge_radius": [0.9, 1.06], "principal_offset": 0.012, "pixel_aspect": [0.98, 1.02]}
# WoodScape's published front-camera calibration (scripts/calibration/front.json of valeoai/WoodScape)
WOODSCAPE_FRONT = {
    "intrinsic": {"model": "radial_poly", "k1": 339.749, "k2": -31.988, "k3": 48.275, "k4": -7.201,
                  "cx_offset": 3.942, "cy_offset": -3.093, "aspect_ratio": 1.0, "width": 1280, "height": 966},
    "extrinsic": {"quaternion": [0.5941767906169857, -0.5878843193897473, 0.3873184109007999, -0.3890121040340926],
                  "translation": [3.7484, 0.0, 0.66017]},
}


def _camera(family: str, seed: int):
    rng = np.random.default_rng(seed)
    intrinsic = sample_intrinsic(rng, family, 640, 480, LENS_CFG)
    cal = {"intrinsic": intrinsic, "extrinsic": {"quaternion": matrix_to_quaternion(mount_rotation(30, 25, 2)),
                                                 "translation": [1.0, 0.5, 0.9]}}
    return camera_from_calibration(cal, "front")


CAMERAS = [_camera(f, s) for f in ("kannala_brandt", "radial_poly") for s in range(3)] + [
    camera_from_calibration(WOODSCAPE_FRONT, "FV")]


def _rays(theta_max_deg: float, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, math.radians(theta_max_deg), n)
    phi = rng.uniform(-math.pi, math.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.intrinsic["model"])
def test_projection_and_back_projection_round_trip_beyond_90_degrees(cam):
    limit = math.degrees(cam.lens.theta_limit)  # where the lens stops being one-to-one
    assert limit > 100
    rays = _rays(100.0, 400, 0)
    uv = cam.project_cam(rays * 5.0)
    back, theta = cam.unproject(uv)
    np.testing.assert_allclose(back, rays, atol=1e-9)
    np.testing.assert_allclose(cam.project_cam(back * 3.0), uv, atol=1e-7)
    assert (theta > math.radians(90)).sum() > 10


@pytest.mark.parametrize("cam", [c for c in CAMERAS if c.intrinsic["model"] == "kannala_brandt"])
def test_kannala_brandt_agrees_with_cv2_fisheye_in_front_of_the_camera(cam):
    i = cam.intrinsic
    K = np.array([[i["fx"], 0, i["cx"]], [0, i["fy"], i["cy"]], [0, 0, 1]], dtype=np.float64)
    D = np.array([i["k1"], i["k2"], i["k3"], i["k4"]], dtype=np.float64)
    pts = _rays(85, 500, 1) * np.random.default_rng(2).uniform(0.5, 30, (500, 1))
    ours = cam.project_cam(pts)
    theirs, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-6)
    # beyond 90 deg cv2's atan(r / z) mirrors the point to the other side of the image; ours does not
    beyond = np.array([[math.sin(math.radians(95)), 0.0, math.cos(math.radians(95))]])
    theirs, _ = cv2.fisheye.projectPoints(beyond.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    assert cam.project_cam(beyond)[0, 0] > i["cx"] > theirs[0, 0, 0]


def test_radial_poly_follows_woodscape_published_formula_and_quaternion_order():
    cam = camera_from_calibration(WOODSCAPE_FRONT)
    i = WOODSCAPE_FRONT["intrinsic"]
    pts = _rays(95, 200, 3) * 4.0
    chi = np.hypot(pts[:, 0], pts[:, 1])
    theta = np.arctan2(chi, pts[:, 2])
    rho = i["k1"] * theta + i["k2"] * theta ** 2 + i["k3"] * theta ** 3 + i["k4"] * theta ** 4
    u = rho * pts[:, 0] / chi + i["cx_offset"] + i["width"] / 2 - 0.5
    v = rho * pts[:, 1] / chi * i["aspect_ratio"] + i["cy_offset"] + i["height"] / 2 - 0.5
    np.testing.assert_allclose(cam.project_cam(pts), np.stack([u, v], 1), atol=1e-9)
    # scalar-last [qx, qy, qz, qw]: the front camera then looks forward and ~23 deg down, x to the right
    forward, right = cam.forward, cam.rotation[:, 0]
    assert forward[0] > 0.9 and math.degrees(math.asin(-forward[2])) == pytest.approx(23.4, abs=0.5)
    assert right[1] < -0.99


def test_quaternion_round_trip_and_behind_the_camera_is_not_mirrored():
    rng = np.random.default_rng(4)
    for _ in range(50):
        q = rng.normal(size=4)
        m = quaternion_to_matrix(q)
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(m)), m, atol=1e-12)
    cam = CAMERAS[0]
    behind_right = cam.translation + 5 * (-cam.forward + 0.3 * cam.rotation[:, 0])
    uv, in_fov = cam.project(behind_right[None])
    assert not in_fov[0] and uv[0, 0] > cam.lens.centre[0]


@pytest.mark.parametrize("cam", CAMERAS[:: 3], ids=lambda c: c.intrinsic["model"])
def test_ground_points_invert_the_projection_of_ground_points(cam):
    rng = np.random.default_rng(5)
    ground = np.concatenate([cam.translation[:2] + rng.uniform(-12, 12, (300, 2)), np.zeros((300, 1))], 1)
    uv, in_fov = cam.project(ground)
    xy, ok = cam.ground_points(uv[in_fov])
    assert ok.all() and in_fov.sum() > 50
    np.testing.assert_allclose(xy, ground[in_fov, :2], atol=1e-6)
    ahead = np.array([cam.forward[0], cam.forward[1], 0.0])
    sky = cam.project(cam.translation + 10 * ahead + np.array([0.0, 0.0, 2.0]))[0]
    assert not cam.ground_points(sky)[1][0]  # a ray going up never reaches the ground


def test_pixel_rays_point_where_the_pixels_are():
    cam = CAMERAS[3]
    rays, valid = cam.pixel_rays()
    assert valid[cam.height // 2, cam.width // 2] and not valid[0, 0]  # black corners of a fisheye
    ys, xs = np.nonzero(valid)
    pick = np.arange(0, len(ys), 997)
    uv, in_fov = cam.project(cam.translation + 3.0 * rays[ys[pick], xs[pick]].astype(np.float64))
    assert in_fov.all()
    np.testing.assert_allclose(uv, np.stack([xs[pick], ys[pick]], 1), atol=1e-3)


def test_a_lens_model_is_one_class_the_calibration_checks_and_cameras_use():
    """A ``LensModel`` subclass registers itself: ``deepword.format_3d`` checks a calibration's fields by it and
    ``camera_from_calibration`` builds its lens, with no other change."""
    from deepword.cameras import LENS_MODELS, FisheyeLens, LensModel, lens_from_intrinsic
    from deepword.format_3d import check_calibration

    class Equidistant(LensModel):   # rho = f theta
        name, fields, positive = "test_equidistant", ("f",), ("f",)

        @classmethod
        def lens(cls, intrinsic):
            return FisheyeLens(poly=(0.0, float(intrinsic["f"])), scale=(1.0, 1.0),
                               centre=(intrinsic["width"] / 2 - 0.5, intrinsic["height"] / 2 - 0.5))

    def fail(field, message):
        raise ValueError(f"{field}: {message}")

    try:
        cal = {"intrinsic": {"model": "test_equidistant", "f": 200.0, "width": 640, "height": 480},
               "extrinsic": {"quaternion": [0.0, 0.0, 0.0, 1.0], "translation": [0.0, 0.0, 1.0]}}
        check_calibration(cal, 640, 480, fail)
        assert lens_from_intrinsic(cal["intrinsic"]).poly == (0.0, 200.0)
        x, y = camera_from_calibration(cal).lens.project(np.array([[1.0, 0.0, 1.0]]))[0]
        assert x == pytest.approx(319.5 + 200.0 * math.pi / 4) and y == pytest.approx(239.5)
        with pytest.raises(ValueError, match=r"calibration.intrinsic.f: missing \(the test_equidistant model needs f"):
            check_calibration({**cal, "intrinsic": {k: v for k, v in cal["intrinsic"].items() if k != "f"}}, 640, 480,
                              fail)
        with pytest.raises(ValueError, match="calibration.intrinsic.f: must be positive"):
            check_calibration({**cal, "intrinsic": {**cal["intrinsic"], "f": -1.0}}, 640, 480, fail)
        with pytest.raises(ValueError, match="registered twice"):
            type("Again", (LensModel,), {"name": "test_equidistant"})
    finally:
        LENS_MODELS.pop("test_equidistant", None)
    with pytest.raises(ValueError, match="must be one of"):
        check_calibration(cal, 640, 480, fail)


def test_an_ego_body_outline_draws_back_the_mask_it_came_from():
    """``ego_body_outline`` (mask -> polygons in box coordinates) and ``Camera.ego_mask`` (polygons -> mask) are
    inverse to within the outline's simplification: the ego's body at the bottom of a fisheye image, and a mirror."""
    mask = np.zeros((120, 160), np.uint8)
    cv2.ellipse(mask, (80, 150), (90, 50), 0, 0, 360, 1, -1)   # the bonnet's curve, cut by the image's bottom
    cv2.rectangle(mask, (0, 30), (12, 60), 1, -1)                 # a mirror at the side
    body = ego_body_outline(mask)
    assert len(body) == 2 and all(len(p) >= 3 for p in body)
    cam = replace(CAMERAS[0], width=160, height=120, ego_body=tuple(tuple(map(tuple, p)) for p in body))
    drawn = cam.ego_mask
    assert drawn.shape == mask.shape
    assert (drawn != mask.astype(bool)).sum() <= 0.03 * mask.sum()
    assert cam.calibration()["ego_body"] == body


def test_an_ego_body_sliver_keeps_an_outline_the_reader_accepts():
    """A strip of the body two pixels wide (area 5) simplifies to a line of two points: its outline is kept
    unsimplified, so the generator never writes an ``ego_body`` its own reader refuses (a held-out frame did)."""
    mask = np.zeros((20, 20), np.uint8)
    mask[5:11, 5:7] = 1
    body = ego_body_outline(mask)
    assert len(body) == 1 and len(body[0]) >= 3

    def fail(field, message):
        raise AssertionError(f"{field}: {message}")

    check_ego_body(body, 20, 20, fail)
    cam = replace(CAMERAS[0], width=20, height=20, ego_body=tuple(tuple(map(tuple, p)) for p in body))
    assert cam.ego_mask[5:11, 5:7].any()

