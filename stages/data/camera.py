"""Kannala-Brandt fisheye cameras (the parameterisation of OpenCV's ``cv2.fisheye``) mounted on the ego.

Projection uses theta = atan2(r, z), the angle off the optical axis, so points beyond 90 deg (a 190 deg
lens sees them) land in the image and points behind the camera are not mirrored in front of it, as they
are with ``cv2.fisheye.projectPoints`` (theta = atan(r / z)). The distortion is
theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), image radius = f theta_d.

Frames: the ego frame has x forward, y left, z up, origin on the ground under the ego's centre. The
camera frame is OpenCV's: x right, y down, z along the optical axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FisheyeCamera:
    name: str
    K: np.ndarray          # 3x3 intrinsics (fx, fy, cx, cy; no skew)
    D: np.ndarray          # k1..k4
    width: int
    height: int
    fov_deg: float
    position: np.ndarray   # camera centre in the ego frame (m)
    R: np.ndarray          # 3x3 rotation ego -> camera: p_cam = R @ (p_ego - position)

    @property
    def theta_max(self) -> float:
        return math.radians(self.fov_deg) / 2

    @property
    def forward(self) -> np.ndarray:
        """The optical axis in the ego frame."""
        return self.R[2]

    def distort(self, theta: np.ndarray) -> np.ndarray:
        t2 = theta * theta
        k1, k2, k3, k4 = self.D
        return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def undistort(self, theta_d: np.ndarray, iters: int = 12) -> np.ndarray:
        """Invert ``distort`` by Newton's method (the polynomial is monotone on [0, pi] for our lenses)."""
        theta = np.array(theta_d, dtype=np.float64, copy=True)
        k1, k2, k3, k4 = self.D
        for _ in range(iters):
            t2 = theta * theta
            f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            theta -= f / df
        return theta

    def project_cam(self, pts_cam: np.ndarray) -> np.ndarray:
        """(N, 3) points in the camera frame -> (N, 2) pixels, defined for every direction but straight back."""
        pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
        r = np.hypot(pts[:, 0], pts[:, 1])
        theta = np.arctan2(r, pts[:, 2])
        scale = np.where(r > 1e-12, self.distort(theta) / np.maximum(r, 1e-12), 0.0)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        return np.stack([fx * pts[:, 0] * scale + cx, fy * pts[:, 1] * scale + cy], axis=1)

    def to_cam(self, pts_ego: np.ndarray) -> np.ndarray:
        return (np.asarray(pts_ego, dtype=np.float64).reshape(-1, 3) - self.position) @ self.R.T

    def project(self, pts_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame points -> (pixels (N, 2), in_fov (N,)): in_fov is False beyond the lens' half field of view."""
        cam = self.to_cam(pts_ego)
        theta = np.arctan2(np.hypot(cam[:, 0], cam[:, 1]), cam[:, 2])
        return self.project_cam(cam), theta <= self.theta_max

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels -> (unit ray directions in the camera frame (N, 3), theta (N,))."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        xd, yd = (uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy
        theta_d = np.hypot(xd, yd)
        theta = self.undistort(theta_d)
        s = np.where(theta_d > 1e-12, np.sin(theta) / np.maximum(theta_d, 1e-12), 0.0)
        return np.stack([xd * s, yd * s, np.cos(theta)], axis=1), theta

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel unit ray directions in the EGO frame (H, W, 3) float32 and the in-FOV mask (H, W)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        rays, theta = self.unproject(np.stack([u.ravel(), v.ravel()], axis=1))
        ego = rays @ self.R  # camera -> ego: R^T applied to row vectors
        valid = theta <= self.theta_max
        return (ego.reshape(self.height, self.width, 3).astype(np.float32),
                valid.reshape(self.height, self.width))


def mount_rotation(yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """Rotation ego -> camera for a camera looking along heading ``yaw`` (0 forward, 90 left), pitched
    ``pitch`` down, rolled ``roll`` about its optical axis."""
    yaw, pitch, roll = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    f0 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down0 = np.array([0.0, 0.0, -1.0])
    forward = math.cos(pitch) * f0 + math.sin(pitch) * down0
    down = math.cos(pitch) * down0 - math.sin(pitch) * f0
    cr, sr = math.cos(roll), math.sin(roll)
    right, down = cr * right + sr * down, -sr * right + cr * down
    return np.stack([right, down, forward])


def camera_from_config(name: str, cam_cfg, width: int, height: int, reference_size) -> FisheyeCamera:
    """Build a camera from its config entry; intrinsics are given at ``reference_size`` and scaled."""
    sx, sy = width / reference_size[0], height / reference_size[1]
    k = cam_cfg["K"]
    K = np.array([[k["fx"] * sx, 0, k["cx"] * sx], [0, k["fy"] * sy, k["cy"] * sy], [0, 0, 1]], dtype=np.float64)
    return FisheyeCamera(
        name=name, K=K, D=np.asarray(cam_cfg["D"], dtype=np.float64), width=width, height=height,
        fov_deg=float(cam_cfg["fov_deg"]), position=np.asarray(cam_cfg["position"], dtype=np.float64),
        R=mount_rotation(cam_cfg["yaw_deg"], cam_cfg["pitch_deg"], cam_cfg.get("roll_deg", 0.0)))
