"""Fisheye camera models and calibrations: the one home of projection and back-projection.

Two lens models, both radial in the angle theta between a ray and the optical axis, each one ``LensModel``
class (registered in ``LENS_MODELS`` by its calibration name):

- ``kannala_brandt`` -- OpenCV's ``cv2.fisheye`` model: r(theta) = theta + k1 theta^3 + k2 theta^5 +
  k3 theta^7 + k4 theta^9; u = fx r x/chi + cx, v = fy r y/chi + cy (chi = sqrt(x^2 + y^2)).
- ``radial_poly`` -- WoodScape's model: rho(theta) = k1 theta + k2 theta^2 + k3 theta^3 + k4 theta^4 in
  pixels; u = rho x/chi + width/2 + cx_offset - 0.5, v = rho y/chi * aspect_ratio + height/2 + cy_offset - 0.5.

Both are one polynomial in theta followed by a diagonal scale and a principal point (``FisheyeLens``). A
``LensModel`` says which calibration fields its model needs and which must be positive (``deepword.format_3d``
checks a calibration with them), builds the lens of a calibration, and writes the calibration of a lens the
generator drew (``stages.data.camera``): adding a lens model is one class here.
theta = atan2(chi, z), so rays beyond 90 deg off-axis (a 190 deg lens sees them) project correctly and rays
behind the camera are not mirrored in front of it, unlike ``cv2.fisheye.projectPoints`` (atan(chi/z)).

Image coordinates are OpenCV's and WoodScape's: the centre of the top-left pixel is (0, 0). The WORD-style
boxes use pixel edges (a box [x1, x2) covers columns x1 .. x2 - 1, the top-left pixel spans [0, 1)), so a
box coordinate is a calibration coordinate + 0.5 (``BOX_TO_IMAGE``).

Frames: the camera frame is OpenCV's (x right, y down, z along the optical axis). A ``Camera`` maps it to
a vehicle frame with ``rotation`` (camera -> vehicle) and ``translation`` (the camera centre in the vehicle
frame): p_vehicle = rotation @ p_camera + translation. In a calibration (WoodScape's convention) the
vehicle frame is ISO 8855: x forward, y left, z up, origin on the ground under the rear axle, and the
extrinsic quaternion is stored scalar-last, [qx, qy, qz, qw] (what ``scipy.spatial.transform.Rotation``
reads; checked against WoodScape's published sample, whose front camera then looks forward and 23 deg
down with its x axis to the vehicle's right).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np

BOX_TO_IMAGE = -0.5  # add to a box coordinate (pixel edges) to get an image coordinate (pixel centres)
_TABLE_SIZE = 4096   # samples of the inverse lens table (refined by Newton steps)


# --- lens ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class FisheyeLens:
    """A radial lens: image point = centre + scale * poly(theta) * (x, y) / chi.

    ``poly`` holds the coefficients of theta^0, theta^1, ... (theta^0 must be 0). ``theta_limit`` is where
    the polynomial stops increasing (or pi): beyond it a radius has no unique angle."""

    poly: tuple[float, ...]
    scale: tuple[float, float]
    centre: tuple[float, float]
    theta_limit: float = field(init=False)

    def __post_init__(self):
        if self.poly[0] != 0:
            raise ValueError("a lens polynomial has no constant term")
        theta = np.linspace(0.0, math.pi, _TABLE_SIZE)
        slope = np.polynomial.polynomial.polyval(theta, np.polynomial.polynomial.polyder(self.poly))
        falling = np.flatnonzero(slope <= 0)
        limit = theta[falling[0] - 1] if len(falling) else math.pi
        if limit <= 0:
            raise ValueError(f"lens polynomial {self.poly} does not increase from theta = 0")
        object.__setattr__(self, "theta_limit", float(limit))

    def radius(self, theta: np.ndarray) -> np.ndarray:
        """Lens radius (in the units ``scale`` maps to pixels) of rays at ``theta`` from the axis: Horner's rule as
        ``np.polynomial.polynomial.polyval`` runs it, to the bit, in place (the footprint fits project millions of
        points, and polyval's temporaries were a third of a projection)."""
        theta = np.asarray(theta, dtype=np.float64)
        r = np.full(theta.shape, float(self.poly[-1]))
        for coef in self.poly[-2::-1]:
            r *= theta
            r += coef
        return r

    def theta_of_radius(self, radius: np.ndarray) -> np.ndarray:
        """Invert ``radius`` on [0, theta_limit]: a table lookup refined by Newton steps; radii beyond the
        limit's give theta_limit."""
        radius = np.asarray(radius, dtype=np.float64)
        table_t = np.linspace(0.0, self.theta_limit, _TABLE_SIZE)
        table_r = self.radius(table_t)
        theta = np.interp(radius, table_r, table_t)
        deriv = np.polynomial.polynomial.polyder(self.poly)
        for _ in range(3):
            step = (self.radius(theta) - radius) / np.maximum(np.polynomial.polynomial.polyval(theta, deriv), 1e-12)
            theta = np.clip(theta - step, 0.0, self.theta_limit)
        return theta

    def project(self, pts_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) image points, for every direction but straight back."""
        pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
        chi = np.hypot(pts[:, 0], pts[:, 1])
        return self.project_polar(pts, chi, np.arctan2(chi, pts[:, 2]))

    def project_polar(self, pts: np.ndarray, chi: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """``project`` of (N, 3) camera-frame points whose distance from the axis ``chi`` and angle ``theta`` from
        it the caller has already computed (``deepword.footprint.silhouette_boxes`` needs them first)."""
        k = np.where(chi > 1e-12, self.radius(theta) / np.maximum(chi, 1e-12), 0.0)
        return np.stack([self.scale[0] * k * pts[:, 0] + self.centre[0],
                         self.scale[1] * k * pts[:, 1] + self.centre[1]], axis=1)

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) image points -> (unit rays in the camera frame (N, 3), theta (N,))."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        a = (uv[:, 0] - self.centre[0]) / self.scale[0]
        b = (uv[:, 1] - self.centre[1]) / self.scale[1]
        radius = np.hypot(a, b)
        theta = self.theta_of_radius(radius)
        s = np.where(radius > 1e-12, np.sin(theta) / np.maximum(radius, 1e-12), 0.0)
        return np.stack([a * s, b * s, np.cos(theta)], axis=1), theta


def kannala_brandt_lens(fx, fy, cx, cy, k1, k2, k3, k4) -> FisheyeLens:
    return FisheyeLens(poly=(0.0, 1.0, 0.0, k1, 0.0, k2, 0.0, k3, 0.0, k4), scale=(fx, fy), centre=(cx, cy))


def radial_poly_lens(k1, k2, k3, k4, cx_offset, cy_offset, aspect_ratio, width, height) -> FisheyeLens:
    return FisheyeLens(poly=(0.0, k1, k2, k3, k4), scale=(1.0, aspect_ratio),
                       centre=(width / 2 + cx_offset - 0.5, height / 2 + cy_offset - 0.5))


# --- lens models: one class each, registered by their calibration name ----------------------------------

LENS_MODELS: dict[str, type[LensModel]] = {}


class LensModel:
    """A calibration's lens model (``calibration.intrinsic.model``). A subclass names itself (``name``, which
    registers it in ``LENS_MODELS``), lists the intrinsic fields it reads beside ``width`` and ``height``
    (``fields``) and those that must be positive (``positive``), and implements ``lens`` (the calibration's
    ``FisheyeLens``) and ``intrinsic`` (the calibration of a lens with a given radial shape, for the generator)."""

    name: ClassVar[str]
    fields: ClassVar[tuple[str, ...]]
    positive: ClassVar[tuple[str, ...]]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.name in LENS_MODELS:
            raise ValueError(f"lens model {cls.name!r} is registered twice ({LENS_MODELS[cls.name].__name__}, "
                             f"{cls.__name__})")
        LENS_MODELS[cls.name] = cls

    @classmethod
    def lens(cls, intrinsic: dict) -> FisheyeLens:
        """The lens of a validated ``intrinsic`` dict of this model."""
        raise NotImplementedError

    @classmethod
    def intrinsic(cls, poly: tuple[float, ...], gain: float, aspect: float, centre_offset: tuple[float, float],
                  width: int, height: int) -> dict:
        """The ``intrinsic`` fields (``model`` first, without width and height) of a lens whose radius is ``gain``
        times the polynomial ``poly`` in theta (coefficients of theta^0, theta^1, ..., the theta coefficient 1, in
        the form this model can hold) in pixels, with a pixel aspect ratio ``aspect`` (y over x) and its principal
        point ``centre_offset`` pixels from the image centre."""
        raise NotImplementedError


class KannalaBrandt(LensModel):
    """OpenCV's ``cv2.fisheye`` model: r(theta) = theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9."""

    name = "kannala_brandt"
    fields = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    positive = ("fx", "fy")

    @classmethod
    def lens(cls, intrinsic: dict) -> FisheyeLens:
        return kannala_brandt_lens(*(float(intrinsic[k]) for k in cls.fields))

    @classmethod
    def intrinsic(cls, poly, gain, aspect, centre_offset, width, height) -> dict:
        return {"model": cls.name, "fx": gain, "fy": gain * aspect, "cx": (width - 1) / 2 + centre_offset[0],
                "cy": (height - 1) / 2 + centre_offset[1], "k1": poly[3], "k2": poly[5], "k3": poly[7], "k4": poly[9]}


class RadialPoly(LensModel):
    """WoodScape's model: rho(theta) = k1 theta + k2 theta^2 + k3 theta^3 + k4 theta^4 pixels."""

    name = "radial_poly"
    fields = ("k1", "k2", "k3", "k4", "cx_offset", "cy_offset", "aspect_ratio")
    positive = ("k1", "aspect_ratio")

    @classmethod
    def lens(cls, intrinsic: dict) -> FisheyeLens:
        return radial_poly_lens(*(float(intrinsic[k]) for k in cls.fields),
                                float(intrinsic["width"]), float(intrinsic["height"]))

    @classmethod
    def intrinsic(cls, poly, gain, aspect, centre_offset, width, height) -> dict:
        if poly[1] != 1.0:
            raise ValueError(f"radial_poly: the shape polynomial's theta coefficient must be 1 (gain scales it), got {poly}")
        return {"model": cls.name, "k1": gain, "k2": gain * poly[2], "k3": gain * poly[3], "k4": gain * poly[4],
                "cx_offset": centre_offset[0], "cy_offset": centre_offset[1], "aspect_ratio": aspect}


def lens_model(name) -> type[LensModel]:
    """The ``LensModel`` class of a calibration model name; a clear error for an unknown one."""
    if not isinstance(name, str) or name not in LENS_MODELS:
        raise ValueError(f"unknown lens model {name!r}; known: {tuple(LENS_MODELS)}")
    return LENS_MODELS[name]


def lens_from_intrinsic(intrinsic: dict) -> FisheyeLens:
    """The lens of a calibration's ``intrinsic`` dict (already validated: see ``deepword.format_3d``)."""
    return lens_model(intrinsic["model"]).lens(intrinsic)


# --- rotations ----------------------------------------------------------------------------------------

def quaternion_to_matrix(q) -> np.ndarray:
    """[qx, qy, qz, qw] (scalar last, normalised here) -> 3x3 rotation matrix."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(m: np.ndarray) -> list[float]:
    """3x3 rotation matrix -> [qx, qy, qz, qw] with qw >= 0 (Shepperd's method: stable for every angle)."""
    m = np.asarray(m, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2 * math.sqrt(1 + tr)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(max(1 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    q = q / np.linalg.norm(q)
    return [float(v) for v in (q if q[3] >= 0 else -q)]


def mount_rotation(yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """Camera -> vehicle rotation of a camera looking along heading ``yaw`` (0 forward, 90 left), pitched
    ``pitch`` down and rolled ``roll`` about its optical axis; its columns are the camera's x (right),
    y (down) and z (optical axis) in the vehicle frame."""
    yaw, pitch, roll = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    f0 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down0 = np.array([0.0, 0.0, -1.0])
    forward = math.cos(pitch) * f0 + math.sin(pitch) * down0
    down = math.cos(pitch) * down0 - math.sin(pitch) * f0
    cr, sr = math.cos(roll), math.sin(roll)
    right, down = cr * right + sr * down, -sr * right + cr * down
    return np.stack([right, down, forward], axis=1)


# --- camera -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Camera:
    """A calibrated fisheye camera: a lens, an image size, a field of view and a pose in a vehicle frame."""

    name: str
    lens: FisheyeLens
    width: int
    height: int
    rotation: np.ndarray      # camera -> vehicle
    translation: np.ndarray   # camera centre in the vehicle frame (m)
    fov_deg: float = 360.0    # rays beyond fov/2 off-axis are not imaged (360: the lens' own limit only)
    intrinsic: dict = field(default_factory=dict)  # the calibration's intrinsic dict this lens came from
    # where the ego vehicle's own body covers the image: polygons of image points (x, y), as boxes are written; the
    # calibration's ``ego_body``. A vehicle seen beyond it is hidden there (deepword.footprint.hidden_edges)
    ego_body: tuple = ()

    @functools.cached_property
    def ego_mask(self) -> np.ndarray | None:
        """(height, width) bool: the pixels ``ego_body`` covers (None without one), drawn once per camera."""
        if not self.ego_body:
            return None
        import cv2  # here, not at the top: most users of a camera never draw its mask

        mask = np.zeros((self.height, self.width), np.uint8)
        cv2.fillPoly(mask, [np.round(np.asarray(p, dtype=np.float64) + BOX_TO_IMAGE).astype(np.int32)
                            for p in self.ego_body], 1)
        return mask.astype(bool)

    @property
    def theta_max(self) -> float:
        return min(math.radians(self.fov_deg) / 2, self.lens.theta_limit)

    @property
    def forward(self) -> np.ndarray:
        """The optical axis in the vehicle frame."""
        return self.rotation[:, 2]

    # the renderer's names: vehicle -> camera rotation and camera position
    @property
    def R(self) -> np.ndarray:
        return self.rotation.T

    @property
    def position(self) -> np.ndarray:
        return self.translation

    def to_cam(self, pts: np.ndarray) -> np.ndarray:
        """Vehicle-frame points (N, 3) -> camera frame."""
        return (np.asarray(pts, dtype=np.float64).reshape(-1, 3) - self.translation) @ self.rotation

    def project_cam(self, pts_cam: np.ndarray) -> np.ndarray:
        return self.lens.project(pts_cam)

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vehicle-frame points -> (image points (N, 2), in_fov (N,)): False beyond the field of view."""
        cam = self.to_cam(pts)
        theta = np.arctan2(np.hypot(cam[:, 0], cam[:, 1]), cam[:, 2])
        return self.lens.project(cam), theta <= self.theta_max

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image points -> (unit rays in the camera frame (N, 3), theta (N,))."""
        return self.lens.unproject(uv)

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image points -> (unit rays in the vehicle frame (N, 3), inside the field of view (N,))."""
        rays, theta = self.lens.unproject(uv)
        return rays @ self.rotation.T, theta <= self.theta_max

    def ground_points(self, uv: np.ndarray, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Back-project image points onto the plane at height ``z``: (N, 2) x, y in the vehicle frame and
        a validity mask (inside the field of view and the ray reaching the plane in front of the camera)."""
        rays, in_fov = self.rays(uv)
        dz = rays[:, 2]
        reaches = (dz * (z - self.translation[2]) > 1e-9) & in_fov
        t = np.where(reaches, (z - self.translation[2]) / np.where(reaches, dz, 1.0), np.nan)
        xy = self.translation[:2] + t[:, None] * rays[:, :2]
        return xy, reaches

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel unit rays in the vehicle frame (H, W, 3) float32 at the pixel centres, and the in-FOV
        mask (H, W)."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        rays, valid = self.rays(np.stack([u.ravel(), v.ravel()], axis=1))
        return (rays.reshape(self.height, self.width, 3).astype(np.float32),
                valid.reshape(self.height, self.width))

    def shifted(self, offset) -> Camera:
        """The same camera in a vehicle frame whose origin lies at ``offset`` in this one."""
        return replace(self, translation=self.translation - np.asarray(offset, dtype=np.float64))

    def calibration(self) -> dict:
        """The WoodScape-convention calibration dict (the frame must be ISO 8855, see ``shifted``)."""
        cal = {"intrinsic": dict(self.intrinsic),
               "extrinsic": {"quaternion": matrix_to_quaternion(self.rotation),
                             "translation": [float(v) for v in self.translation]}}
        if self.ego_body:
            cal["ego_body"] = [[[float(x), float(y)] for x, y in polygon] for polygon in self.ego_body]
        return cal


def ego_body_outline(mask: np.ndarray, tolerance_px: float = 1.0) -> list[list[list[float]]]:
    """A calibration's ``ego_body`` from a mask of the ego's own body in one camera's image ((H, W), nonzero where
    the body is): the outline of each region, simplified to within ``tolerance_px`` (``cv2.approxPolyDP``), in box
    coordinates. ``Camera.ego_mask`` draws it back; regions under 4 square pixels are left out. A sliver two pixels
    wide simplifies to a line of two points, which is no polygon (``format_3d.check_ego_body`` refuses it): it keeps
    its unsimplified outline."""
    import cv2

    contours, _ = cv2.findContours((np.asarray(mask) != 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outlines = []
    for c in contours:
        if cv2.contourArea(c) < 4:
            continue
        simplified = cv2.approxPolyDP(c, tolerance_px, True).reshape(-1, 2)
        points = simplified if len(simplified) >= 3 else c.reshape(-1, 2)
        outlines.append([[float(x) - BOX_TO_IMAGE, float(y) - BOX_TO_IMAGE] for x, y in points])
    return outlines


def camera_from_calibration(calibration: dict, name: str = "") -> Camera:
    """A ``Camera`` from a validated calibration dict (``deepword.format_3d.check_calibration``)."""
    intrinsic = calibration["intrinsic"]
    ext = calibration["extrinsic"]
    return Camera(name=name or str(calibration.get("name", "")), lens=lens_from_intrinsic(intrinsic),
                  width=int(intrinsic["width"]), height=int(intrinsic["height"]),
                  rotation=quaternion_to_matrix(ext["quaternion"]),
                  translation=np.asarray(ext["translation"], dtype=np.float64),
                  fov_deg=float(intrinsic.get("fov_deg", 360.0)), intrinsic=dict(intrinsic),
                  ego_body=tuple(tuple((float(x), float(y)) for x, y in polygon)
                                 for polygon in calibration.get("ego_body", ())))
