"""The generator's camera rig: four fisheye cameras mounted on the ego, nominal or randomised.

The camera models themselves live in ``deepword.cameras``. Here the rig is built in the generator's ego
frame (x forward, y left, z up, origin on the ground under the ego's centre; ``stages.data.synword``
shifts it to the rear axle when it writes calibrations).

Randomised rigs (``data.lens``): per camera a lens family from ``lens.families`` (``kannala_brandt`` or
``radial_poly``), a field of view, the radius its edge reaches as a share of the half image width, a
principal-point offset, a pixel aspect ratio, an image size (width scale x aspect ratio) and a jittered
mount (height, pitch, yaw, roll, position). A rig is drawn from (seed, rig index) alone, so generation
is deterministic and independent of how frames are spread over processes.
"""

from __future__ import annotations

import math

import numpy as np

from deepword.cameras import Camera, lens_from_intrinsic, lens_model, mount_rotation

# The shape of WoodScape's published radial polynomials relative to k1 (its front camera: k2/k1 = -0.094,
# k3/k1 = 0.142, k4/k1 = -0.021), widened: the radial_poly family varies around real lenses.
RADIAL_POLY_SHAPE = {"k2": (-0.15, -0.03), "k3": (0.07, 0.2), "k4": (-0.04, -0.008)}
# Kannala-Brandt distortion coefficients of 170-200 deg lenses (cv2.fisheye calibrations are of this order).
KANNALA_BRANDT_D = {"k1": (-0.02, 0.06), "k2": (-0.012, 0.004), "k3": (-0.001, 0.001), "k4": (-0.0002, 0.0002)}
MONOTONE_MARGIN = math.radians(5)   # a drawn lens must stay one-to-one this far beyond its field of view


def kannala_brandt_shape(rng: np.random.Generator) -> tuple[float, ...]:
    d = [float(rng.uniform(*KANNALA_BRANDT_D[k])) for k in ("k1", "k2", "k3", "k4")]
    return (0.0, 1.0, 0.0, d[0], 0.0, d[1], 0.0, d[2], 0.0, d[3])


def radial_poly_shape(rng: np.random.Generator) -> tuple[float, ...]:
    return (0.0, 1.0, *(float(rng.uniform(*RADIAL_POLY_SHAPE[k])) for k in ("k2", "k3", "k4")))


# The lens families the generator draws (``data.lens.families``): a random radial polynomial of each lens model
# (deepword.cameras.LENS_MODELS), theta coefficient 1; ``sample_intrinsic`` scales it to the image
LENS_SHAPES = {"kannala_brandt": kannala_brandt_shape, "radial_poly": radial_poly_shape}


def nominal_camera(name: str, cam_cfg: dict, width: int, height: int, reference_size) -> Camera:
    """The configured Kannala-Brandt camera (``data.cameras``), intrinsics scaled from ``reference_size``."""
    sx, sy = width / reference_size[0], height / reference_size[1]
    k, d = cam_cfg["K"], [float(v) for v in cam_cfg["D"]]
    # the config's principal point is given in pixel-edge coordinates; the lens uses pixel centres
    intrinsic = {"model": "kannala_brandt", "fx": k["fx"] * sx, "fy": k["fy"] * sy, "cx": k["cx"] * sx - 0.5,
                 "cy": k["cy"] * sy - 0.5, "k1": d[0], "k2": d[1], "k3": d[2], "k4": d[3],
                 "width": int(width), "height": int(height), "fov_deg": float(cam_cfg["fov_deg"])}
    return _camera(name, intrinsic, cam_cfg["position"], cam_cfg["yaw_deg"], cam_cfg["pitch_deg"],
                   cam_cfg.get("roll_deg", 0.0))


def _camera(name, intrinsic: dict, position, yaw, pitch, roll) -> Camera:
    w, h = int(intrinsic["width"]), int(intrinsic["height"])
    return Camera(name=name, lens=lens_from_intrinsic(intrinsic), width=w, height=h, rotation=mount_rotation(yaw, pitch, roll),
                  translation=np.asarray(position, dtype=np.float64), fov_deg=float(intrinsic["fov_deg"]),
                  intrinsic=intrinsic)


def _radius_is_monotone(poly, theta_end: float) -> bool:
    theta = np.linspace(0.0, theta_end, 256)
    slope = np.polynomial.polynomial.polyval(theta, np.polynomial.polynomial.polyder(poly))
    return bool((slope > 0).all())


def sample_intrinsic(rng: np.random.Generator, family: str, width: int, height: int, lens_cfg: dict) -> dict:
    """Draw one lens of ``family`` for a ``width`` x ``height`` image (a calibration ``intrinsic`` dict)."""
    fov = float(rng.uniform(*lens_cfg["fov_deg"]))
    theta_max = math.radians(fov) / 2
    edge_radius = float(rng.uniform(*lens_cfg["edge_radius"])) * width / 2  # pixels where the FOV ends
    off = float(lens_cfg["principal_offset"]) * width
    cx_off, cy_off = (float(v) for v in rng.uniform(-off, off, 2))
    aspect = float(rng.uniform(*lens_cfg["pixel_aspect"]))
    if family not in LENS_SHAPES:
        raise ValueError(f"data.lens.families: unknown lens family {family!r} ({', '.join(LENS_SHAPES)})")
    for _ in range(100):
        poly = LENS_SHAPES[family](rng)
        if _radius_is_monotone(poly, theta_max + MONOTONE_MARGIN):
            break
    else:  # pragma: no cover - the ranges above make a monotone draw all but certain
        raise RuntimeError(f"no one-to-one {family} lens drawn for a {fov:.0f} deg field of view")
    gain = edge_radius / float(np.polynomial.polynomial.polyval(theta_max, poly))
    common = {"width": int(width), "height": int(height), "fov_deg": round(fov, 3)}
    return {**lens_model(family).intrinsic(poly, gain, aspect, (cx_off, cy_off), width, height), **common}


def sample_image_size(rng: np.random.Generator, base_width: int, lens_cfg: dict) -> tuple[int, int]:
    """A width scale and an image aspect ratio from the configured lists; even sizes."""
    scale = float(lens_cfg["width_scales"][rng.integers(len(lens_cfg["width_scales"]))])
    aspect = float(lens_cfg["image_aspects"][rng.integers(len(lens_cfg["image_aspects"]))])
    w = 2 * round(base_width * scale / 2)
    return w, 2 * round(w / aspect / 2)


def sample_camera(rng: np.random.Generator, name: str, mount: dict, lens_cfg: dict, base_width: int) -> Camera:
    """One randomised camera around its configured mount."""
    families = list(lens_cfg["families"])
    family = families[rng.integers(len(families))]
    w, h = sample_image_size(rng, base_width, lens_cfg)
    intrinsic = sample_intrinsic(rng, family, w, h, lens_cfg)
    jit = lens_cfg["mount_jitter"]
    position = np.asarray(mount["position"], dtype=np.float64).copy()
    position[:2] += rng.uniform(-jit["xy_m"], jit["xy_m"], 2)
    position[2] += rng.uniform(-jit["height_m"], jit["height_m"])
    yaw = mount["yaw_deg"] + rng.uniform(-jit["yaw_deg"], jit["yaw_deg"])
    pitch = mount["pitch_deg"] + rng.uniform(-jit["pitch_deg"], jit["pitch_deg"])
    roll = mount.get("roll_deg", 0.0) + rng.uniform(-jit["roll_deg"], jit["roll_deg"])
    return _camera(name, intrinsic, position, yaw, pitch, roll)


def rig_cameras(cfg: dict, seed: int, rig: int, names) -> list[Camera]:
    """The four cameras of rig number ``rig``: randomised when ``cfg['lens']['randomise']``, else nominal."""
    cams, lens_cfg = cfg["cameras"], cfg["lens"]
    w, h = cfg["image_size"]
    if not lens_cfg["randomise"]:
        return [nominal_camera(n, cams[n], w, h, cams["reference_size"]) for n in names]
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1E25, int(rig)]))
    return [sample_camera(rng, n, cams[n], lens_cfg, w) for n in names]


FisheyeCamera = Camera  # the renderer's name for a rig camera
