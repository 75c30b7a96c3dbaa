"""Vehicle footprints in bird's-eye view from the wheels a relation assigns to each vehicle.

A wheel touches the ground, so the image point where its tyre meets the ground, back-projected through the
calibrated fisheye camera onto z = 0, is a metric point (``wheel_contacts``). Per vehicle of a record
(``estimate_record``), from the strongest evidence its relation gives:

- ``sides``: two couples (four wheels): the axis from both side lines, the centre between them;
- ``side``: two wheels of one side (a couple, or two owned wheels as far apart as a wheelbase): the side
  line gives the axis, the wheelbase the length (``FootprintPrior.length_for``), the width prior puts the
  centre behind the side, away from the camera. A couple whose wheels no vehicle box owns (the detector missed or
  cut the vehicle, and found its wheels) is a ``side`` of its own, without a vehicle box (``orphan_sides``);
- ``axle``: two wheels of one axle: the axis is perpendicular, the centre half a wheelbase further away;
- ``wheel``: one wheel: the centre half a wheelbase ahead of a ``rear`` wheel or behind a ``front`` one and
  (width/2 - track inset) to its side; the heading (over 360 deg) and the side are the ones whose vehicle image
  (``Shape``, ``silhouette_boxes``) best fits the vehicle box (``fit_wheel``);
- ``box``: no wheel: the vehicle whose image best fits the vehicle box, searched over its ground position around
  the ``box_bottom`` guess, its axis along the camera's viewing direction (``fit_free``: a vehicle whose wheels
  are all hidden is most often seen end-on), of the two headings the one whose cabin fits best. Where the box ends
  on the ego's own body (the calibration's ``ego_body``), the vehicle may reach beyond that edge unseen
  (``hidden_edges``).

A couple whose contacts lie closer than ``MIN_COUPLE_SHARE`` of the prior's wheelbase is not two axles of one side
(most often one wheel boxed twice, or a wheel whose box is cut): its weaker wheel is left out (``plausible_wheels``).

A weak estimate (``wheel``, ``box``) takes the axis of the nearest footprint of its frame resting on a side's two
wheels within ``CONTEXT_RADIUS_M`` instead (``estimate_frame``, ``context_axes``): vehicles parked in a row or
driving in a lane are parallel.

**Heading direction.** A relation may name each wheel's role (``front`` / ``rear``: DeepWORD's role head and the
ground truth do, the baselines do not). Where the wheels an estimate rests on carry roles that tell the ends apart
(a rear and a front wheel of one side, both wheels of one axle, one wheel's role), its heading points to the
vehicle's front and the estimate is ``directed``; otherwise (``box``: the cabin's fit picks the sign, a guess;
wheels without roles) it is not, and headings are scored both over 360 deg and modulo 180 deg. The facing network
(stage ``facing``; or a detector's facing head) says for each vehicle box which way its front lies in the image
(deepword/facing.py); each estimate's ``facing_vote`` weighs how well its heading, projected through its camera,
agrees with it, in log-odds calibrated on val, and the fusion sums those votes with the roles' and the heading
prior's (``heading_vote``).

**Confidence** (what the detection AP ranks estimates by): ``EVIDENCE_CONFIDENCE`` of the evidence (an ordinal
scale: more wheels, more trust) x the vehicle box's score x the mean score of the wheel boxes used (the
detector's scores on detected boxes, 1 on ground-truth boxes); a no-wheel estimate's also x ``fit_trust`` of its
silhouette fit's cost, a one-wheel estimate's x how sure the fit is of its wheel's end (``end_margin``).

``fuse_frame`` merges a frame's per-camera estimates: estimates within ``fuse_radius_m`` of each other are
one vehicle (seen by two cameras), except two of one image's vehicle boxes, which are two vehicles; its footprint is
the mean of its strongest estimates (the most confident of them where no camera sees a wheel), its heading turned
the way its votes point (``heading_vote``), its confidence the highest of its estimates'; a weak footprint that
another one explains (projected into the cameras that saw the weak one, it draws the boxes they saw: ``absorb_explained``)
joins that one; then confidences are lowered where more confident footprints cover them (``suppress_overlaps``:
vehicles do not overlap on the ground).
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from shapely.geometry import Polygon

from deepword.cameras import BOX_TO_IMAGE, Camera
from deepword.facing import image_facing, record_facing, record_facing_accuracy
from deepword.format_3d import Box3D
from deepword.wheel_roles import network_roles
from deepword.word_format import VEHICLE, WHEEL, Record

# evidence levels, strongest first
EVIDENCE = ("sides", "side", "axle", "wheel", "box")
EVIDENCE_CONFIDENCE = {"sides": 1.0, "side": 0.9, "axle": 0.7, "wheel": 0.5, "box": 0.3}
EVIDENCE_WHEELS = {"sides": 2, "side": 2, "axle": 2, "wheel": 1, "box": 0}   # wheels the evidence rests on (cap 2)
# A no-wheel estimate's confidence falls with its silhouette fit's cost (``fit_trust``): exp(-cost / FIT_COST_SCALE).
# Its position rests on the vehicle box alone, and a box the prior-shaped vehicle cannot fit (cut by the image's
# edge, hidden in part, a long or odd body) places it worst. Chosen on the train and val splits (docs/bev.md,
# "Confidence"); the scale only orders no-wheel estimates among themselves and against the detector's scores.
FIT_COST_SCALE = 0.1
# A couple is two axles of one side when its contacts lie at least this share of the prior's wheelbase apart: closer,
# the couple's axis is noise (on detected boxes the side estimates whose axis was 20-90 deg off implied median lengths
# of 2.1-3.4 m, the right ones 4.5 m: docs/bev.md, "Couples without a vehicle, and couples too short"). Chosen on two
# datasets' val and test splits (not the run's own): 0.54-0.75 gained on detected boxes, 0.86 lost 0.4-0.5 AP on
# labelled ones.
MIN_COUPLE_SHARE = 0.7
# A couple no vehicle box owns gives a footprint at this share of a ``side`` estimate's confidence: the vehicle box
# that would confirm it is missing (0.25-1 measured; 0.5 best, docs/bev.md).
ORPHAN_CONFIDENCE = 0.5
# A couple whose implied length lies outside this band of the prior's length (x 0.8-1.25) must explain its vehicle
# box's left and right edges (``side_fits_box``: cost at most SIDE_FIT_MAX_COST, as ``silhouette_cost`` counts it on
# those two edges), else it is taken for one wheel of each of two vehicles and the vehicle is fitted from its box
# alone. Only the horizontal edges: a bus's couple is right, and the car-shaped silhouette misses its height. Chosen on
# four datasets the run never trained on, in domain and held out (docs/bev.md, "Couples without a vehicle, and couples
# too short": "A couple that does not fit its box").
SIDE_LENGTH_BAND = (0.8, 1.25)
SIDE_FIT_MAX_COST = 0.1


@dataclass(frozen=True)
class FootprintPrior:
    """Vehicle shape statistics fitted on the train split's 3D truth (``fit_prior``)."""

    width: float              # median vehicle width (m)
    length: float             # median length
    wheelbase: float          # median wheelbase
    length_slope: float       # length = length_slope * wheelbase + length_offset (least squares)
    length_offset: float
    track_inset: float        # median distance from a wheel's contact point in to the body side
    contact_shift: float      # how much nearer the camera the back-projected wheel point lies than the contact, at 0 m
    box_shift: float          # median distance from the back-projected vehicle box bottom centre on to the centre
    height: float = 1.5       # median vehicle height (footprints are boxes of this height)
    # the contact shift grows with distance: ``contact_shift`` + ``contact_slope`` x the back-projected distance
    # (``fit_contact_shift``); 0: one shift at every distance
    contact_slope: float = 0.0
    # the silhouette model (``Shape``): chosen on the train split's vehicle boxes at their true poses
    clearance: float = 0.25   # the lower body's bottom (m)
    belt: float = 0.55        # the lower body's top (share of the height)
    cabin_length: float = 0.65  # the cabin's length (share of the length)
    cabin_x: float = -0.1     # the cabin's centre ahead of the body's (share of the length)
    # which way vehicles face where (``heading_prior_logit``): per cell of the vehicle frame and axis class, the share
    # of the train split's vehicles facing the class's canonical way ("par,ix,iy" -> share; "par" -> the class's share)
    heading: dict | None = None

    @property
    def shape(self) -> Shape:
        return Shape(self.clearance, self.belt, self.cabin_length, self.cabin_x, self.wheelbase / self.length)

    def length_for(self, wheelbase: float) -> float:
        return self.length_slope * wheelbase + self.length_offset

    def to_json(self) -> dict:
        out = {k: round(float(v), 5) for k, v in asdict(self).items() if k != "heading"}
        if self.heading:
            out["heading"] = {k: round(float(v), 4) for k, v in self.heading.items()}
        return out

    @classmethod
    def from_json(cls, d: dict) -> FootprintPrior:
        fields = {k: float(d[k]) for k in cls.__dataclass_fields__ if k in d and k != "heading"}
        return cls(**fields, heading={str(k): float(v) for k, v in d["heading"].items()} if d.get("heading") else None)


@dataclass(frozen=True)
class Estimate:
    """One vehicle's estimated footprint from one image."""

    box: Box3D
    evidence: str           # one of EVIDENCE
    camera: str
    vehicle_box_id: int | None   # None: a couple of wheels no vehicle box owns (``orphan_sides``)
    image: str
    confidence: float = 1.0  # EVIDENCE_CONFIDENCE x the vehicle box's score x the used wheels' mean score (x fit_trust
    #                          for a no-wheel estimate); after fusion x what suppress_overlaps leaves
    role_vote: float = 0.0   # log-odds, from the wheels' roles, that ``box.yaw`` points to the front (0: no roles)
    facing_vote: float = 0.0  # log-odds, from a network's facing vector, that ``box.yaw`` points to the front
    # what the camera saw: the camera and the vehicle box (x1, y1, x2, y2; None for an orphan couple), so that the
    # fusion can ask whether another camera's footprint explains this view (``absorb_explained``)
    cam: Camera | None = field(default=None, compare=False, repr=False)
    vbox: tuple[float, float, float, float] | None = field(default=None, compare=False)
    contacts: tuple[tuple[float, float], ...] = field(default=(), compare=False)   # the ground points of its wheels

    @property
    def rank(self) -> int:
        return EVIDENCE.index(self.evidence)

    @property
    def directed(self) -> bool:
        """The wheels' roles or the detector's facing voted for the heading's direction (else only the axis came from
        the wheels or the box)."""
        return self.role_vote != 0.0 or self.facing_vote != 0.0


# --- image points -> ground ---------------------------------------------------------------------------

def _away(cam: Camera, xy: np.ndarray) -> np.ndarray:
    """Unit horizontal directions from the camera to ground points (N, 2)."""
    d = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - cam.translation[:2]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


def bottom_points(cam: Camera, xyxy: np.ndarray) -> np.ndarray:
    """(N, 2) image points where boxes meet the ground: the box bottom centres, moved along the image's own
    'down' (the direction a vertical line runs at that place of the fisheye image) to the box border."""
    xyxy = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4) + BOX_TO_IMAGE
    centre = np.stack([(xyxy[:, 0] + xyxy[:, 2]) / 2, (xyxy[:, 1] + xyxy[:, 3]) / 2], axis=1)
    # the local image direction of "down": a point on the centre's ray and the same point lowered a little
    rays, _ = cam.rays(centre)
    p = cam.translation + 3.0 * rays
    a, _ = cam.project(p)
    b, _ = cam.project(p - np.array([0.0, 0.0, 0.05]))
    down = b - a
    down /= np.maximum(np.linalg.norm(down, axis=1, keepdims=True), 1e-9)
    down[down[:, 1] < 0.2] = (0.0, 1.0)  # a degenerate direction falls back to the image's own down
    half = (xyxy[:, 2:] - xyxy[:, :2]) / 2
    # walk from the centre along `down` to the first box edge
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.minimum(np.where(np.abs(down[:, 0]) > 1e-9, half[:, 0] / np.abs(down[:, 0]), np.inf),
                       np.where(np.abs(down[:, 1]) > 1e-9, half[:, 1] / np.abs(down[:, 1]), np.inf))
    return centre + t[:, None] * down


def wheel_contacts(cam: Camera, xyxy: np.ndarray, prior: FootprintPrior | None) -> tuple[np.ndarray, np.ndarray]:
    """Ground contact points (N, 2) of wheel boxes and their validity; with a prior, each point moves away from
    the camera by the fitted shift at its distance, ``contact_shift`` + ``contact_slope`` x the distance (a tyre's
    lowest visible point lies nearer the camera than the middle of its footprint, the more so the further it is)."""
    xy, ok = cam.ground_points(bottom_points(cam, xyxy))
    if prior is not None:
        distance = np.linalg.norm(xy - cam.translation[:2], axis=1, keepdims=True)
        xy = xy + (prior.contact_shift + prior.contact_slope * distance) * _away(cam, xy)
    return xy, ok


def box_bottom_points(cam: Camera, xyxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground points of the vehicle boxes' bottom centres."""
    return cam.ground_points(bottom_points(cam, xyxy))


# --- one vehicle --------------------------------------------------------------------------------------

def _axis_angle(v: np.ndarray) -> float:
    return math.atan2(v[1], v[0])


def _edge_axis(cam: Camera, box: np.ndarray, prior: FootprintPrior) -> float | None:
    """The axis from a vehicle box's bottom edge: its back-projected bottom corners span the vehicle's visible
    side (along the axis) when they lie further apart than the width and less far than the length."""
    x1, _, x2, y2 = box + BOX_TO_IMAGE
    xy, ok = cam.ground_points(np.array([[x1, y2], [x2, y2]]))
    if not ok.all():
        return None
    edge = xy[1] - xy[0]
    span = float(np.linalg.norm(edge))
    along = _axis_angle(edge)
    return along if span >= (prior.length + prior.width) / 2 else along + math.pi / 2


def box_bottom_estimate(cam: Camera, box: np.ndarray, prior: FootprintPrior) -> Box3D | None:
    p, ok = box_bottom_points(cam, box[None, :4])
    if not ok[0]:
        return None
    centre = p[0] + prior.box_shift * _away(cam, p)[0]
    yaw = _edge_axis(cam, box[:4], prior)
    return Box3D(float(centre[0]), float(centre[1]), prior.length, prior.width, 0.0 if yaw is None else yaw)


# --- fitting a vehicle's shape to its image box ------------------------------------------------------------

# points along each of a cuboid's 12 edges (shares of the edge): corners, midpoints and quarter points, enough for the
# bbox of a fisheye-curved edge
_EDGE_STEPS = (0.0, 0.25, 0.5, 0.75, 1.0)
# per box edge (x1, y1, x2, y2): the cost of a projected edge beyond the seen box, against 1 inside it (a vehicle's
# image is at least its seen box; a hidden part may explain more: a nearer vehicle hides the bottom of the ones
# behind it); chosen on the train split
BEYOND_WEIGHT = (0.5, 0.25, 0.5, 0.25)


def _cuboid(x: tuple, y: tuple, z: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Edge points of a cuboid whose bounds are linear in the vehicle's size: each bound (coefficient of the size,
    offset in m). Returns (coefficients (P, 3), offsets (P, 3)): a point = coefficients * (length, width, height)
    + offsets."""
    corners = [(x[i], (y[0], y[1]) if j == 0 else (-y[0], -y[1]), z[k]) for k in (0, 1)
               for i, j in ((1, 0), (1, 1), (0, 1), (0, 0))]
    coef = np.array([[cx[0], cy[0], cz[0]] for cx, cy, cz in corners])
    off = np.array([[cx[1], cy[1], cz[1]] for cx, cy, cz in corners])
    edges = [(i, (i + 1) % 4) for i in range(4)] + [(4 + i, 4 + (i + 1) % 4) for i in range(4)] + [(i, i + 4) for i in range(4)]
    t = np.array(_EDGE_STEPS)[:, None]
    return (np.concatenate([coef[a] + t * (coef[b] - coef[a]) for a, b in edges]),
            np.concatenate([off[a] + t * (off[b] - off[a]) for a, b in edges]))


@dataclass(frozen=True)
class Shape:
    """A vehicle's silhouette model (its defaults fit the train split's vehicle boxes at their true poses to
    under a pixel, median, on the left, right and top edges): the lower body from ``clearance`` (m) up to
    ``belt`` (share of the height), the full length and width; the cabin above it up to the height, ``cabin_length``
    (share of the length) long, its centre ``cabin_x`` (share of the length) ahead of the body's centre, 8 cm
    narrower on each side; the wheels' lowest points on the ground, ``wheelbase`` (share of the length) apart."""

    clearance: float = 0.25
    belt: float = 0.55
    cabin_length: float = 0.65
    cabin_x: float = -0.1
    wheelbase: float = 0.6

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(coefficients, offsets) of the silhouette's edge points (``_cuboid``); computed once per shape (a fit asks
        for them thousands of times); read-only."""
        return _shape_points(self)


_WHEEL_POINTS = 4   # the silhouette's points after its edges' (``_shape_points``): each wheel's lowest point


@functools.cache
def _shape_points(shape: Shape) -> tuple[np.ndarray, np.ndarray]:
    """``Shape.points``, computed once per shape (shapes are frozen and few)."""
    lower = _cuboid(((-0.5, 0.0), (0.5, 0.0)), (0.5, 0.0), ((0.0, shape.clearance), (shape.belt, 0.0)))
    cx0, cx1 = shape.cabin_x - shape.cabin_length / 2, shape.cabin_x + shape.cabin_length / 2
    cabin = _cuboid(((cx0, 0.0), (cx1, 0.0)), (0.5, -0.08), ((shape.belt, 0.0), (1.0, 0.0)))
    half = shape.wheelbase / 2
    wheels = (np.array([[sx * half, sy * 0.5, 0.0] for sx in (1, -1) for sy in (1, -1)]),
              np.array([[0.0, -sy * 0.1, 0.0] for _ in (1, -1) for sy in (1, -1)]))
    assert len(wheels[0]) == _WHEEL_POINTS
    coef = np.concatenate([lower[0], cabin[0], wheels[0]])
    off = np.concatenate([lower[1], cabin[1], wheels[1]])
    coef.flags.writeable = off.flags.writeable = False
    return coef, off


def silhouette_boxes(cam: Camera, xy: np.ndarray, yaw: np.ndarray, size, shape: Shape) -> np.ndarray:
    """(N, 4) image boxes (box coordinates, clipped to the image) of vehicles of ``shape`` and ``size`` (length,
    width, height; (3,) or (N, 3)) standing at ground centres ``xy`` (N, 2) heading ``yaw`` (N,): the bbox of the
    projected edge points within the field of view and of the points where an edge leaves it (``_fov_crossings``:
    where the image of a half-seen vehicle ends, on the border of the lens' image circle). A vehicle wholly beyond
    the field of view is the bbox of its points moved onto that border."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    size = np.asarray(size, dtype=np.float64).reshape(-1, 3)
    coef, off = shape.points()
    local = coef[None] * size[:, None, :] + off[None]   # (N, P, 3); (1, P, 3) for one size: the points once
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    world = np.stack(np.broadcast_arrays(xy[:, :1] + c * local[..., 0] - s * local[..., 1],
                                         xy[:, 1:] + s * local[..., 0] + c * local[..., 1], local[..., 2]),
                     axis=2).reshape(-1, 3)
    pc = cam.to_cam(world)
    chi = np.hypot(pc[:, 0], pc[:, 1])
    theta = np.arctan2(chi, pc[:, 2])   # the lens' own angle too (project_polar): computed once
    n, points = len(xy), len(pc) // max(len(xy), 1)
    keep = None
    if (theta > cam.theta_max).any():
        crossings, crossed = _fov_crossings(cam, pc.reshape(n, points, 3), theta.reshape(n, points))
        keep = np.concatenate([theta.reshape(n, points) <= cam.theta_max, crossed], axis=1)
        keep[~keep.any(axis=1), :points] = True   # wholly beyond the field of view: its points, moved onto the border
        _onto_border(cam, pc, chi, theta)
        crossing_chi = np.hypot(crossings[..., 0], crossings[..., 1])   # only the new points' angles are computed
        pc = np.concatenate([pc.reshape(n, points, 3), crossings], axis=1).reshape(-1, 3)
        chi = np.concatenate([chi.reshape(n, points), crossing_chi], axis=1).reshape(-1)
        theta = np.concatenate([theta.reshape(n, points), np.arctan2(crossing_chi, crossings[..., 2])],
                               axis=1).reshape(-1)
    # (2, N, P): u and v each with a vehicle's points contiguous, so that the bbox is four row reductions (a fit asks
    # for thousands of silhouettes; reducing (N, P, 2) over its middle axis took a fifth of the bev stage)
    uv = np.ascontiguousarray(cam.lens.project_polar(pc, chi, theta).T).reshape(2, n, -1) - BOX_TO_IMAGE
    if keep is None:
        boxes = np.concatenate([uv.min(axis=2).T, uv.max(axis=2).T], axis=1)
    else:
        boxes = np.concatenate([np.where(keep, uv, np.inf).min(axis=2).T, np.where(keep, uv, -np.inf).max(axis=2).T],
                               axis=1)
    return np.clip(boxes, 0.0, [cam.width, cam.height, cam.width, cam.height])


_CROSSING_BISECTIONS = 10   # a crossing within 1/1024 of its quarter edge (~1 mm of a 5 m car's side)


def _fov_crossings(cam: Camera, pc: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the silhouette's edges cross the border of the field of view: for vehicles' camera-frame points ``pc``
    (N, P, 3) (the edge points of ``Shape.points``, each edge ``_EDGE_STEPS`` long, then the four wheel points) and
    their angles ``theta`` off the axis (N, P), the point of each step of an edge whose ends lie either side of
    ``theta_max`` (bisection) and whether it does: ((N, S, 3), (N, S)) over every step S.

    Why not move a point beyond the border onto it along its own azimuth: a vehicle cut by the image circle is seen
    up to where its edges meet the border, while the azimuths of the parts beyond can run far along the circle. Moved
    there, the bottom of a car at the side of a fisheye's circle stood 50-100 px below its seen box, and a fit
    placed it metres too far away to shrink its image."""
    steps = len(_EDGE_STEPS)
    n, points = theta.shape
    edges = (points - _WHEEL_POINTS) // steps
    ends = pc[:, :edges * steps].reshape(n, edges, steps, 3)
    angle = theta[:, :edges * steps].reshape(n, edges, steps)
    inside = angle <= cam.theta_max
    crossed = inside[:, :, :-1] != inside[:, :, 1:]
    a, b = ends[:, :, :-1][crossed], ends[:, :, 1:][crossed]   # (C, 3) each: the two ends of each crossing step
    a_in = inside[:, :, :-1][crossed][:, None]
    inner, step = np.where(a_in, a, b), np.where(a_in, b - a, a - b)   # from the inside end towards the outside one
    lo, hi = np.zeros((len(a), 1)), np.ones((len(a), 1))     # lo: on the inside end's side, hi: beyond
    cos_t, sin_t = math.cos(cam.theta_max), math.sin(cam.theta_max)
    for _ in range(_CROSSING_BISECTIONS):
        mid = (lo + hi) / 2
        p = inner + mid * step
        beyond = (p[:, 2] * sin_t < np.hypot(p[:, 0], p[:, 1]) * cos_t)[:, None]   # its angle off the axis > theta_max
        lo, hi = np.where(beyond, lo, mid), np.where(beyond, mid, hi)
    out = np.zeros((n, edges, steps - 1, 3))
    out[crossed] = inner + lo * step
    return out.reshape(n, -1, 3), crossed.reshape(n, -1)


def _onto_border(cam: Camera, pc: np.ndarray, chi: np.ndarray, theta: np.ndarray) -> None:
    """Camera-frame points beyond the field of view moved onto its border along their azimuth, in place (``chi``
    and ``theta`` with them)."""
    beyond = np.flatnonzero(theta > cam.theta_max)
    if len(beyond):
        tm = cam.theta_max
        scale = math.sin(tm) / np.maximum(chi[beyond], 1e-12)
        pc[beyond] = np.stack([pc[beyond, 0] * scale, pc[beyond, 1] * scale, np.full(len(beyond), math.cos(tm))],
                              axis=1)
        chi[beyond] = np.hypot(pc[beyond, 0], pc[beyond, 1])
        theta[beyond] = np.arctan2(chi[beyond], pc[beyond, 2])


def silhouette_cost(pred: np.ndarray, seen: np.ndarray, edges: list[int] | None = None,
                    hidden: np.ndarray | None = None) -> np.ndarray:
    """(N,) mismatch of projected boxes ``pred`` (N, 4) with the seen vehicle box ``seen`` (4,): squared edge
    distances in shares of the seen box's larger side, an edge beyond the seen box weighted ``BEYOND_WEIGHT``, or 0
    where ``hidden`` (4,) says something hides what lies beyond that edge (``hidden_edges``); summed over ``edges``
    (indices of x1, y1, x2, y2; all four when None)."""
    seen = np.asarray(seen[:4], dtype=np.float64)
    d = (pred - seen) / max(float(seen[2] - seen[0]), float(seen[3] - seen[1]), 1.0)
    d[:, :2] = -d[:, :2]                      # positive: the projection reaches beyond the seen box
    beyond = np.asarray(BEYOND_WEIGHT) if hidden is None else np.where(hidden, 0.0, BEYOND_WEIGHT)
    w = np.where(d > 0, beyond, 1.0)
    cost = w * d * d
    return (cost if edges is None else cost[:, edges]).sum(axis=1)


# a seen box's edge is where the vehicle ends only if nothing hides what lies beyond it: where the ego's own body
# (``Camera.ego_body``) covers at least EGO_BAND_SHARE of the EGO_BAND_PX pixels just beyond an edge, the vehicle may
# reach beyond it unseen. On three datasets' val splits a third of the no-wheel views within 10 m (side cameras
# mostly) end on the ego's body, their true bottom a median 28-34 px below the seen one; fitted as if they ended
# there they stood a median 2.0-2.2 m off, with the edge free 0.9-1.3 m (docs/bev.md, "Vehicles the ego's body
# hides"). Only the no-wheel fit (``fit_free``) frees them: a one-wheel fit's contact pins the position
EGO_BAND_PX = 4
EGO_BAND_SHARE = 0.3


def hidden_edges(cam: Camera, box: np.ndarray) -> np.ndarray | None:
    """(4,) bool per edge of ``box`` (x1, y1, x2, y2): whether the ego's body hides what lies just beyond it;
    None for a camera without an ``ego_body``."""
    mask = cam.ego_mask
    if mask is None:
        return None
    h, w = mask.shape
    x1, y1, x2, y2 = (int(round(float(v))) for v in box[:4])
    x1, x2, y1, y2 = max(x1, 0), min(x2, w), max(y1, 0), min(y2, h)
    bands = (mask[y1:y2, max(x1 - EGO_BAND_PX, 0):x1], mask[max(y1 - EGO_BAND_PX, 0):y1, x1:x2],
             mask[y1:y2, x2:x2 + EGO_BAND_PX], mask[y2:y2 + EGO_BAND_PX, x1:x2])
    return np.array([band.size > 0 and float(band.mean()) >= EGO_BAND_SHARE for band in bands])


def side_fits_box(cam: Camera, box: Box3D, vbox: np.ndarray, prior: FootprintPrior) -> bool:
    """Whether a side's footprint ``box`` (from two wheels' contacts) may be the vehicle ``vbox`` shows: its length
    lies within ``SIDE_LENGTH_BAND`` of the prior's, or the silhouette of a vehicle that long (``_size``) meets the
    box's left and right edges (``SIDE_FIT_MAX_COST``)."""
    share = box.length / prior.length
    if SIDE_LENGTH_BAND[0] <= share <= SIDE_LENGTH_BAND[1]:
        return True
    pred = silhouette_boxes(cam, [[box.x, box.y]], [box.yaw], _size(prior, share), prior.shape)
    return float(silhouette_cost(pred, vbox, edges=[0, 2], hidden=hidden_edges(cam, vbox))[0]) <= SIDE_FIT_MAX_COST


def _size(prior: FootprintPrior, scale: float = 1.0) -> tuple[float, float, float]:
    """The prior's (length, width, height), a longer vehicle's at ``scale`` > 1: length and height times ``scale``,
    width times 1 + (scale - 1) / 3 (long vehicles are taller, not much wider)."""
    return prior.length * scale, prior.width * (1 + (scale - 1) / 3), prior.height * scale


# a one-wheel or no-wheel vehicle's size is searched too: the prior's (scale 1) and longer, taller ones (buses, long
# vans: the in-domain prior knows only cars); a longer size must fit the vehicle box better by SIZE_PENALTY per unit of
# scale (silhouette cost), chosen on the val split (ground-truth boxes and relations: AP within 10 m 83.2 without the
# search, 83.8 with 0.01-0.03, 83.2 with 0.1). Coarse to fine: the best of SIZE_SCALES, then its neighbours
# SIZE_REFINE_STEP either side (not under 1). A car 10 % longer than the median one, fitted at 1.0 or 1.3, stood ~0.5 m
# too far; on three datasets' val splits the refinement took the no-wheel median centre error from 0.568 / 0.272 /
# 0.226 to 0.386 / 0.225 / 0.209 m (labelled boxes). A grid in steps of 0.1 did as well in domain but fitted long
# vehicles as cars (a bus at 1.6 came out at 1.1, 1.9 m off) and lost held out (docs/bev.md, "Sizes")
SIZE_SCALES = (1.0, 1.3, 1.6, 1.9, 2.2)
SIZE_REFINE_STEP = 0.1
SIZE_PENALTY = 0.03


_SHARED_FITS: dict | None = None   # ``shared_fits``: fit_sized's answers by their exact inputs, while it is open


@contextlib.contextmanager
def shared_fits():
    """Within it, ``fit_sized`` remembers each answer by its exact inputs and gives it again: the bev stage estimates
    every method's footprints on the same boxes, where most vehicles are fitted alike (their wheels assigned alike),
    and the size search makes a fit the costliest step. The same numbers come out as without it."""
    global _SHARED_FITS
    outer, _SHARED_FITS = _SHARED_FITS, ({"fits": {}, "pinned": {}} if _SHARED_FITS is None else _SHARED_FITS)
    try:
        yield
    finally:
        _SHARED_FITS = outer


def _fit_key(value, pinned: dict):
    """A hashable stand-in for one argument of a fit: arrays by content, objects (the camera, the prior) by identity,
    kept alive in ``pinned`` so that no other object takes their id while the memo lives."""
    if isinstance(value, np.ndarray):
        return value.dtype.str, value.shape, value.tobytes()
    if isinstance(value, list | tuple):
        return tuple(_fit_key(v, pinned) for v in value)
    if isinstance(value, Camera | FootprintPrior):
        pinned[id(value)] = value
        return type(value).__name__, id(value)
    return value


def fit_sized(fit, *args, scales: tuple[float, ...] = SIZE_SCALES) -> tuple[Box3D, float]:
    """``fit`` (``fit_free`` or ``fit_wheel``) over the vehicle sizes ``scales`` (``_size``) and then the best one's
    neighbours ``SIZE_REFINE_STEP`` either side (not under 1): the fit whose silhouette cost plus ``SIZE_PENALTY`` x
    (scale - 1) is lowest; returns its box and silhouette cost. Within ``shared_fits``, a fit of the same inputs is
    computed once."""
    if _SHARED_FITS is None:
        return _fit_sized(fit, args, scales)
    fits = _SHARED_FITS["fits"]
    key = (fit.__name__, _fit_key(args, _SHARED_FITS["pinned"]), scales)
    if key not in fits:
        fits[key] = _fit_sized(fit, args, scales)
    return fits[key]


def _fit_sized(fit, args: tuple, scales: tuple[float, ...]) -> tuple[Box3D, float]:
    def scored(scale: float) -> tuple[float, float, Box3D, float]:   # (penalised cost, scale, box, cost)
        box, cost = fit(*args, scale=scale)
        return cost + SIZE_PENALTY * (scale - 1), scale, box, cost

    # min keeps the first of equals: a coarse size over its neighbours, the shorter of two coarse sizes
    best = min((scored(s) for s in scales), key=lambda t: t[0])
    neighbours = [round(best[1] + d, 6) for d in (-SIZE_REFINE_STEP, SIZE_REFINE_STEP)]
    best = min([best, *(scored(s) for s in neighbours if s >= 1.0 and s not in scales)], key=lambda t: t[0])
    return best[2], best[3]


def fit_free(cam: Camera, vbox: np.ndarray, prior: FootprintPrior, start: Box3D,
             axes: list[float] | None = None, scale: float = 1.0) -> tuple[Box3D, float]:
    """A no-wheel footprint: the prior-shaped vehicle whose image best fits the vehicle box (``silhouette_cost``),
    searched coarse to fine over its ground position around ``start``, its axis one of ``axes`` (its neighbours'),
    else along the camera's viewing direction (a vehicle whose wheels are all hidden is most often seen from its
    front or back); of the two headings along an axis, the one whose cabin fits best."""
    size, hidden = _size(prior, scale), hidden_edges(cam, vbox)
    bx, by = start.x, start.y
    span, step_m = 2.4, 0.6
    fixed = np.array([a + t for a in (axes or []) for t in (0.0, math.pi)])
    turns = np.array([0.0, math.pi])
    for _ in range(4):
        off = np.arange(-span, span + 1e-9, step_m)
        gx, gy = np.meshgrid(bx + off, by + off, indexing="ij")
        xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
        if len(fixed):
            xy, yaw = np.repeat(xy, len(fixed), axis=0), np.tile(fixed, len(xy))
        else:
            view = np.arctan2(xy[:, 1] - cam.translation[1], xy[:, 0] - cam.translation[0])
            xy, yaw = np.repeat(xy, len(turns), axis=0), (view[:, None] + turns[None]).ravel()
        costs = silhouette_cost(silhouette_boxes(cam, xy, yaw, size, prior.shape), vbox, hidden=hidden)
        i = int(np.argmin(costs))
        bx, by, cost = float(xy[i, 0]), float(xy[i, 1]), float(costs[i])
        turn = float(yaw[i]) - math.atan2(by - cam.translation[1], bx - cam.translation[0])
        fixed, turns = (np.array([yaw[i]]), turns) if len(fixed) else (fixed, np.array([turn]))
        span, step_m = step_m, step_m / 3
    return Box3D(bx, by, size[0], size[1], math.remainder(float(yaw[i]), 2 * math.pi)), cost


def _one_wheel_centres(contact: np.ndarray, yaw: np.ndarray, along: np.ndarray, side: np.ndarray, half_wb: float,
                       lateral: float) -> np.ndarray:
    """(N, 2) centres of vehicles heading ``yaw`` whose wheel touches the ground at ``contact``: ``along`` (+-1) half a
    wheelbase ahead of it (+1) or behind it, ``side`` (+-1) ``lateral`` to its left (+1) or right."""
    u = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    return contact + along[:, None] * u * half_wb + side[:, None] * n * lateral


def fit_wheel(cam: Camera, contact: np.ndarray, role: str | None, vbox: np.ndarray,
              prior: FootprintPrior, axes: list[float] | None = None, scale: float = 1.0) -> tuple[Box3D, float]:
    """A one-wheel footprint: the wheel sits (wheelbase/2) ahead of the centre when ``front``, behind it when
    ``rear`` (both tried without a role), (width/2 - track inset) to one side; the vehicle whose image best fits the
    vehicle box over both sides and every heading, or the two along one of ``axes`` (its neighbours'). The heading
    points to the front."""
    size = _size(prior, scale)
    half_wb, lateral = prior.wheelbase * scale / 2, size[1] / 2 - prior.track_inset
    along = {"front": (-1.0,), "rear": (1.0,)}.get(role, (-1.0, 1.0))   # centre = contact + a * u * half_wb ...
    yaws = np.array([a + t for a in axes for t in (0.0, math.pi)]) if axes else np.arange(72) * math.pi / 36
    for it in range(1 if axes else 3):
        cand = np.array([(y, a, b) for y in yaws for a in along for b in (-1.0, 1.0)])
        xy = _one_wheel_centres(contact, cand[:, 0], cand[:, 1], cand[:, 2], half_wb, lateral)
        # every edge counts here, hidden or not: the contact pins the position, and freeing a hidden edge let the
        # side and heading search pick worse (AP of one-wheel vehicles down on two of three datasets' val splits)
        costs = silhouette_cost(silhouette_boxes(cam, xy, cand[:, 0], size, prior.shape), vbox)
        i = int(np.argmin(costs))
        step = math.pi / 36 / 4 ** it
        yaws = cand[i, 0] + np.linspace(-4 * step, 4 * step, 9)
        along = (cand[i, 1],)
    return (Box3D(float(xy[i, 0]), float(xy[i, 1]), size[0], size[1], math.remainder(float(cand[i, 0]), 2 * math.pi)),
            float(costs[i]))


# A one-wheel footprint's centre lies half a wheelbase to one side of its wheel, and where the fit picks the wrong side
# the footprint stands a wheelbase off, as confident as a right one: end to end, most false positives near the 95 %
# precision point. Its confidence is therefore x (1 - exp(-margin / END_MARGIN_SCALE)), the margin being how much worse
# the box is drawn from the wheel's other end (``end_margin``). Chosen on the val and train splits of three datasets,
# end to end (`deepword infer --detect`) and on labelled boxes (docs/bev.md, "Confidence"): 0.03 raised the recall at
# 95 % precision on all twelve or held it, and AP on eleven
END_MARGIN_SCALE = 0.03


def centre_ahead_of(box: Box3D, xy) -> float:
    """How far (m) ``box``'s centre lies ahead of the ground point ``xy`` along its heading (< 0: behind it)."""
    return float(np.dot(np.array([box.x, box.y]) - xy, (math.cos(box.yaw), math.sin(box.yaw))))


def end_margin(cam: Camera, contact: np.ndarray, box: Box3D, cost: float, vbox: np.ndarray,
               prior: FootprintPrior) -> float:
    """How much worse (silhouette cost) the vehicle box ``vbox`` is drawn by the one-wheel footprint ``box`` (its
    cost ``cost``) turned to the other end of its wheel at ``contact``: the centre on the other side of the contact
    along the axis, the axis within 10 deg of ``box``'s either way, the wheel on either side; 0 where that is as good."""
    scale = box.length / prior.length
    size = _size(prior, scale)
    half_wb, lateral = prior.wheelbase * scale / 2, size[1] / 2 - prior.track_inset
    chosen = math.copysign(1.0, centre_ahead_of(box, contact))
    yaws = np.concatenate([box.yaw + np.radians(np.linspace(-10, 10, 9)) + t for t in (0.0, math.pi)])
    cand = np.array([(y, b) for y in yaws for b in (-1.0, 1.0)])
    along = -chosen * np.sign(np.cos(cand[:, 0] - box.yaw))   # the other side of the wheel, in each candidate's heading
    xy = _one_wheel_centres(contact, cand[:, 0], along, cand[:, 1], half_wb, lateral)
    costs = silhouette_cost(silhouette_boxes(cam, xy, cand[:, 0], size, prior.shape), vbox)
    return max(float(costs.min()) - cost, 0.0)


CONTEXT_RADIUS_M = 8.0   # a weak estimate takes the axis of the nearest footprint resting on two wheels this close


def context_axes(context: list[Box3D] | None, xy: np.ndarray, radius_m: float = CONTEXT_RADIUS_M) -> list[float]:
    """The axis of the nearest of a frame's ``context`` footprints (those resting on two or more wheels) within
    ``radius_m`` of ``xy``: neighbouring vehicles (a parking row, a lane) are most often parallel."""
    near = [(math.hypot(b.x - xy[0], b.y - xy[1]), b.yaw) for b in context or []]
    near = [n for n in near if 0.5 < n[0] <= radius_m]
    return [min(near)[1]] if near else []


def _side_box(cam: Camera, a: np.ndarray, b: np.ndarray, prior: FootprintPrior, far_side: bool = True) -> Box3D:
    """Footprint from two same-side contacts: the body lies beyond the side line, away from the camera."""
    axis = b - a
    wheelbase = float(np.linalg.norm(axis))
    u = axis / max(wheelbase, 1e-9)
    n = np.array([-u[1], u[0]])
    mid = (a + b) / 2
    if far_side and np.dot(n, mid - cam.translation[:2]) < 0:
        n = -n
    centre = mid + n * (prior.width / 2 - prior.track_inset)
    return Box3D(float(centre[0]), float(centre[1]), prior.length_for(wheelbase), prior.width, _axis_angle(u))


def _axle_box(cam: Camera, a: np.ndarray, b: np.ndarray, prior: FootprintPrior) -> Box3D:
    """Footprint from the two contacts of one axle: the vehicle extends away from the camera."""
    axle = b - a
    n = np.array([-axle[1], axle[0]]) / max(float(np.linalg.norm(axle)), 1e-9)
    mid = (a + b) / 2
    if np.dot(n, mid - cam.translation[:2]) < 0:
        n = -n
    centre = mid + n * prior.wheelbase / 2
    return Box3D(float(centre[0]), float(centre[1]), prior.length, prior.width, _axis_angle(n))


def _mean_box(boxes: list[Box3D]) -> Box3D:
    """Mean centre, size and undirected axis (doubled-angle mean) of footprints of one vehicle."""
    x = float(np.mean([b.x for b in boxes]))
    y = float(np.mean([b.y for b in boxes]))
    yaw = 0.5 * math.atan2(sum(math.sin(2 * b.yaw) for b in boxes), sum(math.cos(2 * b.yaw) for b in boxes))
    return Box3D(x, y, float(np.mean([b.length for b in boxes])), float(np.mean([b.width for b in boxes])), yaw,
                 float(np.mean([b.height for b in boxes])))


def _flip(box: Box3D) -> Box3D:
    return replace(box, yaw=math.remainder(box.yaw + math.pi, 2 * math.pi))


# How far the relation network's roles are trusted, as log-odds that the direction they give is right: measured on
# the quick profile's val split (ground-truth boxes) with the shipped role head, whose front probabilities stay
# within 0.4-0.6: a couple's order (rear first) is right for 61 % of the couples, one wheel's role for 56 %.
ROLE_COUPLE_LOGIT = 0.45
ROLE_WHEEL_LOGIT = 0.25


def _ordered(a: int, b: int, roles: dict[int, str], couple: bool) -> tuple[int, int, float]:
    """Two same-side wheels rear first when their roles tell, with the vote (log-odds) that the order is right: two
    different roles; else, for a couple of a record whose relations carry roles, its listed order (a relation network
    with a role head lists couples rear first, by its front probabilities). 0: nothing tells (as given)."""
    ra, rb = roles.get(a), roles.get(b)
    if (ra, rb) == ("front", "rear"):
        return b, a, ROLE_COUPLE_LOGIT
    if (ra, rb) == ("rear", "front"):
        return a, b, ROLE_COUPLE_LOGIT
    return a, b, (ROLE_COUPLE_LOGIT if couple and ra is not None and rb is not None else 0.0)


def orient(box: Box3D, headings: list[float]) -> Box3D:
    """``box`` with its heading turned the way most of the directed ``headings`` point."""
    if headings and sum(math.cos(h - box.yaw) for h in headings) < 0:
        return _flip(box)
    return box


def record_contacts(rec: Record, cam: Camera, prior: FootprintPrior | None) -> dict[int, np.ndarray]:
    """{wheel box_id: ground contact (x, y)} of the record's wheels whose contact is found (``wheel_contacts``)."""
    wheels = rec.boxes[rec.class_ids == WHEEL]
    if not len(wheels):
        return {}
    xy, ok = wheel_contacts(cam, wheels[:, :4], prior)
    return {int(w[6]): xy[i] for i, w in enumerate(wheels) if ok[i]}


def estimate_record(rec: Record, cam: Camera, prior: FootprintPrior, use_relations: bool = True,
                    context: list[Box3D] | None = None) -> list[Estimate]:
    """One footprint per vehicle box of ``rec`` from its predicted relations and couples
    (``use_relations=False``: the ``box_bottom`` baseline)."""
    contacts = record_contacts(rec, cam, prior) if use_relations else {}
    return footprints_from_contacts(rec, cam, prior, contacts, use_relations, context)


def footprints_from_contacts(rec: Record, cam: Camera, prior: FootprintPrior, contacts: dict[int, np.ndarray],
                             use_relations: bool = True, context: list[Box3D] | None = None,
                             weak: bool = True) -> list[Estimate]:
    """``estimate_record`` given the wheels' ground contact points (wheel box_id -> (x, y)); ``weak=False``: only
    the vehicles resting on two or more wheels."""
    if use_relations:
        rec = plausible_wheels(rec, contacts, prior)
    by_id = {int(b[6]): b for b in rec.boxes}
    facings = record_facing(rec) if use_relations else {}
    facing_acc, facing_scale = record_facing_accuracy(rec, FACING_VAL_ACC), rec.extra.get(FACING_SCALE_KEY)
    owner = rec.owner_of() if use_relations else {}
    roles = network_roles(rec) if use_relations else {}   # not the roles read from a heading: one vote is enough
    # a role head lists couples rear first: their order is a (weak) vote when the relations carry roles
    couple_order = set(rec.wheel_pairs) if roles else set()
    couples = [(a, b) for a, b in rec.wheel_pairs if a in contacts and b in contacts] if use_relations else []
    side_threshold = (prior.wheelbase + prior.width) / 2
    out = []
    for vid in (int(b[6]) for b in rec.boxes if int(b[5]) == VEHICLE):
        vbox = by_id[vid]
        wheels = [w for w, v in owner.items() if v == vid and w in contacts]
        own_couples = [(a, b) for a, b in couples if owner.get(a) == vid and owner.get(b) == vid]
        box, evidence, vote, used, fit_cost = None, "box", 0.0, [], None
        if len(own_couples) >= 2:
            ordered = [_ordered(a, b, roles, (a, b) in couple_order) for a, b in own_couples[:2]]
            sides = [_side_box(cam, contacts[a], contacts[b], prior, far_side=False) for a, b, _ in ordered]
            centre = np.mean([contacts[w] for pair in own_couples[:2] for w in pair], axis=0)
            merged = _mean_box(sides)
            box, evidence = Box3D(float(centre[0]), float(centre[1]), merged.length, prior.width, merged.yaw), "sides"
            votes = [(s.yaw, v) for s, (_, _, v) in zip(sides, ordered, strict=True) if v]
            box = orient(box, [h for h, _ in votes])
            vote = sum(v * math.copysign(1.0, math.cos(h - box.yaw)) for h, v in votes)
            used = [w for pair in own_couples[:2] for w in pair]
        elif len(wheels) >= 2:
            if own_couples:
                a, b = own_couples[0]
            else:  # the two owned wheels furthest apart
                a, b = max(((p, q) for i, p in enumerate(wheels) for q in wheels[i + 1:]),
                           key=lambda pq: np.linalg.norm(contacts[pq[0]] - contacts[pq[1]]))
            apart = float(np.linalg.norm(contacts[a] - contacts[b]))
            used = [a, b]
            if own_couples or apart >= side_threshold:
                a, b, vote = _ordered(a, b, roles, (a, b) in couple_order)
                box, evidence = _side_box(cam, contacts[a], contacts[b], prior), "side"
            else:
                box, evidence = _axle_box(cam, contacts[a], contacts[b], prior), "axle"
                axle_roles = {roles.get(a), roles.get(b)}
                vote = ROLE_WHEEL_LOGIT if len(axle_roles) == 1 and None not in axle_roles else 0.0
                if axle_roles == {"front"}:  # the body extends back from the front axle: the front faces the camera
                    box = _flip(box)
        elif not weak:
            continue
        elif len(wheels) == 1:
            # the position from the vehicle box alone (a role this unsure would put the centre a wheelbase off);
            # the role, where there is one, votes for the direction
            role, c = roles.get(wheels[0]), contacts[wheels[0]]
            box, cost = fit_sized(fit_wheel, cam, c, None, vbox, prior, context_axes(context, c))
            evidence, used, vote = "wheel", wheels, 0.0
            # how sure the fit is of the wheel's end (END_MARGIN_SCALE): a wrong end puts the centre a wheelbase off
            end_trust = 1.0 - math.exp(-end_margin(cam, c, box, cost, vbox, prior) / END_MARGIN_SCALE)
            if role is not None:
                points_front = (centre_ahead_of(box, c) < 0) == (role == "front")   # the centre lies behind a front wheel
                vote = ROLE_WHEEL_LOGIT if points_front else -ROLE_WHEEL_LOGIT
        if evidence in ("sides", "side") and not side_fits_box(cam, box, vbox, prior):
            # one wheel of each of two vehicles: the vehicle is fitted from its box alone, and gives no context
            if not weak:
                continue
            box = None
        if box is None:
            start = box_bottom_estimate(cam, vbox, prior)
            box, evidence, vote, used = start, "box", 0.0, []
            if start is not None and use_relations:
                box, fit_cost = fit_sized(fit_free, cam, vbox, prior, start, context_axes(context, (start.x, start.y)))
        if box is not None:
            box = replace(box, height=prior.height * (box.length / prior.length if evidence in ("wheel", "box") else 1.0))
            conf = EVIDENCE_CONFIDENCE[evidence] * float(vbox[4])
            if used:
                conf *= float(np.mean([by_id[w][4] for w in used]))
            if evidence == "wheel":
                conf *= end_trust
            if evidence == "box" and fit_cost is not None:
                # how sure the fit is counts every edge of the box: a vehicle whose bottom the ego's body hides was
                # placed by its other edges alone and is less sure than one that explains its whole box
                hidden = hidden_edges(cam, vbox)
                conf *= fit_trust(seen_cost(cam, box, vbox, prior) if hidden is not None and hidden.any() else fit_cost)
            out.append(Estimate(box=box, evidence=evidence, camera=rec.camera, vehicle_box_id=vid, image=rec.image,
                                confidence=conf, role_vote=vote,
                                facing_vote=facing_vote(cam, box, facings.get(vid), facing_acc, facing_scale),
                                cam=cam, vbox=tuple(float(v) for v in vbox[:4]),
                                contacts=tuple((float(contacts[w][0]), float(contacts[w][1])) for w in used)))
    if use_relations:
        out += orphan_sides(rec, cam, prior, contacts, owner, roles, couple_order)
    return out


def plausible_wheels(rec: Record, contacts: dict[int, np.ndarray], prior: FootprintPrior) -> Record:
    """``rec`` without the weaker wheel (lower score; the second on labelled boxes) of each couple whose contacts lie
    closer than ``MIN_COUPLE_SHARE`` x the prior's wheelbase: no vehicle's two axles stand that close, so the couple's
    line is no side (one wheel boxed twice, a cut box). The wheel leaves the couples and the relations; its box stays."""
    score = {int(b[6]): float(b[4]) for b in rec.boxes}
    shortest = MIN_COUPLE_SHARE * prior.wheelbase
    dropped = {min((b, a), key=lambda w: score[w]) for a, b in rec.wheel_pairs
               if a in contacts and b in contacts and float(np.linalg.norm(contacts[a] - contacts[b])) < shortest}
    if not dropped:
        return rec
    return replace(rec, relations=[r for r in rec.relations if r[1] not in dropped],
                   wheel_pairs=[(a, b) for a, b in rec.wheel_pairs if a not in dropped and b not in dropped])


def orphan_sides(rec: Record, cam: Camera, prior: FootprintPrior, contacts: dict[int, np.ndarray],
                 owner: dict[int, int], roles: dict[int, str], couple_order: set) -> list[Estimate]:
    """A ``side`` estimate (``vehicle_box_id`` None) for each couple of ``rec`` neither of whose wheels a vehicle box
    owns: the detector found the wheels and missed the vehicle (cut by the image's edge, hidden behind another), and
    the relation network still paired them. Confidence ``ORPHAN_CONFIDENCE`` x a side's x the wheels' mean score."""
    score = {int(b[6]): float(b[4]) for b in rec.boxes}
    out = []
    for a, b in rec.wheel_pairs:
        if a in owner or b in owner or a not in contacts or b not in contacts:
            continue
        a, b, vote = _ordered(a, b, roles, (a, b) in couple_order)
        # the prior's height, as a side estimate of a vehicle box gets: a footprint is a box with a height
        box = replace(_side_box(cam, contacts[a], contacts[b], prior), height=prior.height)
        out.append(Estimate(box=box, evidence="side", camera=rec.camera,
                            vehicle_box_id=None, image=rec.image,
                            confidence=EVIDENCE_CONFIDENCE["side"] * ORPHAN_CONFIDENCE * (score[a] + score[b]) / 2,
                            role_vote=vote))
    return out



# --- which way a vehicle faces: the roles' votes and where it stands ------------------------------------------

HEADING_CELL_M = 5.0      # the heading prior's cells (m) of the vehicle frame
HEADING_RANGE_M = 20.0    # train vehicles within this range of the vehicle frame's origin make the heading prior
HEADING_SMOOTHING = 4.0   # a cell's share is pulled towards its axis class's share by this many pseudo-vehicles


def _heading_key(yaw: float, x: float, y: float) -> tuple[str, str, bool]:
    """(cell key, axis class key, whether ``yaw`` faces the class's canonical way): the axis class is ``1`` along the
    vehicle frame's x axis (canonical: +x) and ``0`` across it (canonical: +y)."""
    axis = math.remainder(yaw, math.pi)                # (-pi/2, pi/2]
    along = abs(math.cos(axis)) >= math.sqrt(0.5)
    canonical = axis if along or math.sin(axis) > 0 else axis + math.pi
    facing = abs(math.remainder(yaw - canonical, 2 * math.pi)) < math.pi / 2
    par = str(int(along))
    return f"{par},{math.floor(x / HEADING_CELL_M)},{math.floor(y / HEADING_CELL_M)}", par, facing


def fit_heading(vehicles: list[Box3D]) -> dict[str, float]:
    """The heading prior from true vehicles: per axis class its share facing the canonical way; per cell (within
    HEADING_RANGE_M) its share, pulled towards its class's by HEADING_SMOOTHING pseudo-vehicles."""
    cells, classes = {}, {}
    for v in vehicles:
        if math.hypot(v.x, v.y) > HEADING_RANGE_M:
            continue
        cell, par, facing = _heading_key(v.yaw, v.x, v.y)
        for table, key in ((cells, cell), (classes, par)):
            n, k = table.get(key, (0, 0))
            table[key] = (n + 1, k + facing)
    shares = {par: (k + 1) / (n + 2) for par, (n, k) in classes.items()}
    out = dict(shares)
    for cell, (n, k) in cells.items():
        out[cell] = (k + HEADING_SMOOTHING * shares[cell.split(",")[0]]) / (n + HEADING_SMOOTHING)
    return out


def heading_prior_logit(prior: FootprintPrior | None, box: Box3D) -> float:
    """Log-odds, from where ``box`` stands and its axis, that its heading points to the front: vehicles in the lanes
    beside the ego mostly drive its way, parked rows mostly share theirs (``FootprintPrior.heading``, fitted on the
    train split's 3D truth); 0 without a heading prior."""
    if prior is None or not prior.heading:
        return 0.0
    cell, par, facing = _heading_key(box.yaw, box.x, box.y)
    share = prior.heading.get(cell, prior.heading.get(par, 0.5))
    share = min(max(share, 1e-3), 1 - 1e-3)
    logit = math.log(share / (1 - share))
    return logit if facing else -logit


# How far a detector's facing head is trusted (its records carry no ``FACING_SCALE_KEY`` nor
# ``deepword.facing.FACING_ACC_KEY``; the facing network's carry both): measured on the quick profile's val split with
# `detector.facing=true` (docs/detector.md, "Facing"): the head points within 90 deg of the truth for FACING_VAL_ACC of
# the detected vehicles matched to a true one (387; 65 % at the true centre cells), and its vectors' length hardly
# tells the right ones from the wrong. To be measured again when the head changes.
FACING_VAL_ACC = 0.57
MAX_FACING_ACC = 0.99  # no facing vote counts for more than this: a measured 100 % on val is still a sample


def facing_logit(accuracy: float) -> float:
    """The log-odds a facing vector of measured ``accuracy`` (0-1) votes with: 0 at chance or below."""
    p = min(max(float(accuracy), 0.5), MAX_FACING_ACC)
    return math.log(p / (1 - p))


FACING_LOGIT = facing_logit(FACING_VAL_ACC)
# A record's extra key: the factor, fitted on val (the facing stage's temperature scaling), that turns a facing vector's
# projection onto a unit image direction into the log-odds that the vehicle's front lies that way
FACING_SCALE_KEY = "facing_scale"


def facing_vote(cam: Camera, box: Box3D, facing: list[float] | None, accuracy: float = FACING_VAL_ACC,
                scale: float | None = None) -> float:
    """Log-odds, from a network's facing vector of the vehicle box (``deepword.facing``: image pixels, its length the
    network's certainty), that ``box.yaw`` points to the front. With ``scale`` (``FACING_SCALE_KEY``: the facing
    network's): ``scale`` x the vector's projection onto the image direction of ``box``'s own heading through ``cam``,
    within +-``facing_logit(MAX_FACING_ACC)``; without (a detector's vectors): ``facing_logit(accuracy)`` (their
    measured accuracy) x the cosine between the two x the vector's length (at most 1). 0 without a vector or where
    the heading's image direction is not defined."""
    if facing is None:
        return 0.0
    f = np.asarray(facing, dtype=np.float64)
    strength = float(np.hypot(f[0], f[1]))
    if not strength > 1e-6:
        return 0.0
    d = image_facing(cam, box.x, box.y, box.yaw, box.length)
    if d is None:
        return 0.0
    if scale is not None:
        cap = facing_logit(MAX_FACING_ACC)
        return float(np.clip(float(scale) * float(np.dot(d, f)), -cap, cap))
    return facing_logit(accuracy) * float(np.dot(d, f)) / strength * min(strength, 1.0)


def heading_vote(box: Box3D, group: list[Estimate], prior: FootprintPrior | None) -> float:
    """Log-odds that ``box.yaw`` points to the front: the roles' and the detector's facing votes of the estimates of
    one vehicle (every camera that saw it), each turned to ``box``'s axis, plus where it stands
    (``heading_prior_logit``)."""
    votes = sum((e.role_vote + e.facing_vote) * math.copysign(1.0, math.cos(e.box.yaw - box.yaw))
                for e in group if e.directed)
    return votes + heading_prior_logit(prior, box)


def camera_agreement(fused: list[tuple[Box3D, list[Estimate]]]) -> tuple[int, int]:
    """(pairs, agreeing) over the fused vehicles whose facing was voted from two or more cameras: each pair of those
    cameras, and how many pairs point the vehicle the same way (a camera's votes summed, each turned to the vehicle's
    axis). A check of the facing network that needs no labels: if it is right for a share p of vehicles, independently
    per camera, two cameras agree with probability p^2 + (1 - p)^2 (``implied_accuracy``)."""
    pairs = agreeing = 0
    for box, group in fused:
        per_camera: dict[str, float] = {}
        for e in group:
            if e.facing_vote != 0.0:
                turned = e.facing_vote * math.copysign(1.0, math.cos(e.box.yaw - box.yaw))
                per_camera[e.camera] = per_camera.get(e.camera, 0.0) + turned
        votes = [v for v in per_camera.values() if v != 0.0]
        for i, a in enumerate(votes):
            for b in votes[i + 1:]:
                pairs += 1
                agreeing += (a > 0) == (b > 0)
    return pairs, agreeing


def implied_accuracy(pairs: int, agreeing: int) -> float | None:
    """The facing network's accuracy (0.5-1) that would make ``agreeing`` of ``pairs`` cameras agree
    (``camera_agreement``); 0.5 where they agree half the time or less, None without pairs. Errors of two cameras
    on one vehicle go together more often than independence says, so it reads a few points high: on the quick run's
    labelled test boxes 0.90 in domain (3D truth: 0.87), 0.73 on the held-out domain (0.69)."""
    if pairs == 0:
        return None
    return 0.5 + 0.5 * math.sqrt(max(2.0 * agreeing / pairs - 1.0, 0.0))


# Fewer camera pairs than this say too little about the facing network to act on (``facing_trust``) or warn about.
MIN_CAMERA_PAIRS = 20
# How far (percentage points) under the facing network's val accuracy ``implied_accuracy`` may read before its votes
# are weighed down (``facing_trust``) and ``deepword infer`` warns: on the quick run's test sets (val accuracy
# 92.1 %) it read 90.4 / 87.6 % in domain (labelled / detected boxes), 73.2 / 76.3 % on the held-out domain.
FACING_DOUBT_POINTS = 8.0


def facing_trust(fused: list[tuple[Box3D, list[Estimate]]], val_accuracy: float) -> float:
    """The factor the facing votes of these footprints (a run's frames, one box source) are to be weighed by: 1 while
    the cameras' agreement (``camera_agreement``) implies an accuracy within ``FACING_DOUBT_POINTS`` of the network's
    ``val_accuracy`` (0-1) or rests on fewer than ``MIN_CAMERA_PAIRS`` pairs; else the log-odds of the implied
    accuracy over those of the val accuracy (0 at chance), the weight a vote of that accuracy would have."""
    return agreement_trust(*camera_agreement(fused), val_accuracy)


def agreement_trust(pairs: int, agreeing: int, val_accuracy: float) -> float:
    """``facing_trust`` from an agreement already counted (``camera_agreement``'s pairs and agreeing pairs)."""
    implied = implied_accuracy(pairs, agreeing)
    if implied is None or pairs < MIN_CAMERA_PAIRS or 100 * implied >= 100 * val_accuracy - FACING_DOUBT_POINTS:
        return 1.0
    return facing_logit(implied) / max(facing_logit(val_accuracy), 1e-9)


def weigh_facing(estimates: list[Estimate], weight: float) -> list[Estimate]:
    """The estimates with their facing votes times ``weight`` (``facing_trust``), to fuse again: a frame's fusion
    from its estimates (``fuse_frame``) is cheap beside the fits that made them."""
    return estimates if weight == 1.0 else [replace(e, facing_vote=e.facing_vote * weight) for e in estimates]


def refuse_weighed(frames: dict, weight: float, radius_m: float, prior: FootprintPrior | None) -> dict:
    """{frame: (estimates, fused footprints)} with each frame fused again from its estimates, their facing votes times
    ``weight`` (``weigh_facing``); the same frames where ``weight`` is 1."""
    if weight == 1.0:
        return frames
    return {f: (est, fuse_frame(weigh_facing(est, weight), radius_m, prior)) for f, (est, _) in frames.items()}


# --- a frame's cameras ----------------------------------------------------------------------------------

CONTEXT_EVIDENCE = ("sides", "side")   # the footprints whose axes the weak estimates of their frame may take


def estimate_frame(views: list[tuple[Record, Camera]], prior: FootprintPrior, use_relations: bool = True,
                   contacts: list[dict[int, np.ndarray]] | None = None) -> list[Estimate]:
    """``estimate_record`` for each (record, camera) of one frame, the weak estimates (one wheel, none) with the
    axes of the frame's footprints resting on a side's two wheels (``context_axes``) as their context. ``contacts``:
    the wheels' ground contacts per view (``wheel_contacts`` when not given)."""
    if contacts is None:
        contacts = [record_contacts(rec, cam, prior) if use_relations else {} for rec, cam in views]
    context = [e.box for (rec, cam), found in zip(views, contacts, strict=True)
               for e in footprints_from_contacts(rec, cam, prior, found, use_relations, weak=False)
               if e.evidence in CONTEXT_EVIDENCE] if use_relations else None
    return [e for (rec, cam), found in zip(views, contacts, strict=True)
            for e in footprints_from_contacts(rec, cam, prior, found, use_relations, context)]


def same_vehicle(lead: Box3D, other: Box3D, radius_m: float) -> bool:
    """Whether ``other`` (a weaker or equal estimate) is the vehicle of a group led by ``lead``: their centres lie within
    ``radius_m``, or along ``lead``'s axis within ``radius_m`` plus half of what ``lead`` is longer than ``other`` (and
    across it within ``radius_m``). Cameras that see different wheels of one long
    vehicle (a bus) place a shorter estimate near the end they see, up to (lead length - its length) / 2 from the
    long footprint's centre; for two car-sized estimates this is the plain radius."""
    if math.hypot(lead.x - other.x, lead.y - other.y) <= radius_m:
        return True
    c, s = math.cos(lead.yaw), math.sin(lead.yaw)
    dx, dy = other.x - lead.x, other.y - lead.y
    along, across = abs(c * dx + s * dy), abs(-s * dx + c * dy)
    return across <= radius_m and along <= radius_m + max(0.0, (lead.length - other.length) / 2)


def two_boxes_of_one_image(a: Estimate, b: Estimate) -> bool:
    """Whether ``a`` and ``b`` come from two vehicle boxes of one image: a detector (or an annotator) boxes two
    vehicles there, so however close their estimates lie they are not one vehicle."""
    return (a.image == b.image and a.vehicle_box_id is not None and b.vehicle_box_id is not None
            and a.vehicle_box_id != b.vehicle_box_id)


def fuse_frame(estimates: list[Estimate], radius_m: float,
               prior: FootprintPrior | None = None) -> list[tuple[Box3D, list[Estimate]]]:
    """Group estimates of one frame whose centres lie within ``radius_m`` of a group's strongest estimate, along a
    longer one's axis up to half the difference in length further (``same_vehicle``: the ends of a bus) (strongest
    evidence first, then the camera that saw the vehicle nearest), never two of one image's vehicle boxes
    (``two_boxes_of_one_image``); each group -> one footprint, the mean of its estimates of the strongest evidence
    (where that is ``box``, no camera seeing a wheel, the most confident of them: a view that the image circle or a
    nearer object cuts fits worse; docs/bev.md), its heading turned the way the group's votes point (``heading_vote``:
    every estimate's roles, and with ``prior`` where the vehicle stands), else the way its leading estimate points;
    with ``prior``, each weak footprint another one explains joins that one (``absorb_explained``); the groups'
    estimates' confidences then lowered where footprints overlap (``suppress_overlaps``)."""
    def nearness(e: Estimate) -> float:
        return math.hypot(e.box.x, e.box.y)

    groups: list[list[Estimate]] = []
    for e in sorted(estimates, key=lambda e: (e.rank, nearness(e))):
        for g in groups:
            if same_vehicle(g[0].box, e.box, radius_m) and not any(two_boxes_of_one_image(x, e) for x in g):
                g.append(e)
                break
        else:
            groups.append([e])
    fused = []
    for g in groups:
        top = [e for e in g if e.rank == g[0].rank]
        if len(top) == 1:
            box = top[0].box
        elif top[0].evidence == "box":   # no wheel anywhere: the best-trusted view (fit_trust), not the mean
            box = max(top, key=lambda e: e.confidence).box
        else:
            box = orient(_mean_box([e.box for e in top]), [top[0].box.yaw])
        if heading_vote(box, g, prior) < 0:
            box = _flip(box)
        fused.append((box, g))
    if prior is not None:
        fused = absorb_explained(fused, prior)
    return suppress_overlaps(fused)


# A weak footprint (one wheel or none) is a second footprint of a vehicle another footprint places where that one,
# projected into each camera that saw the weak one, draws the box that camera saw (within EXPLAINED_COST of
# ``silhouette_cost``) and holds the ground contacts of the wheels it rests on (within CONTACT_MARGIN_M), their
# centres within ABSORB_RADIUS_M. A weak view's place along its camera's ray is its least sure part (an end-on
# vehicle's length, a one-wheel fit's choice of end, a box the image circle cuts), so fusing by ground distance
# (``fuse_radius_m``) left two footprints of one vehicle 1.5-4 m apart, the weak one a confident false positive; what
# a camera is sure of is the box it saw and where a wheel touches the ground. Chosen on the val and train splits of
# three datasets (labelled boxes and relations; docs/bev.md, "One vehicle, two footprints"): AP and precision up on
# all six, the recall at 95 % precision up or level; the cost bound from the pairs' costs (same vehicle: median 0.09,
# other vehicles: 1.3).
EXPLAINED_COST = 0.03
ABSORB_RADIUS_M = 5.0
CONTACT_MARGIN_M = 0.5
WEAK_EVIDENCE = ("wheel", "box")


def explained_cost(box: Box3D, e: Estimate, prior: FootprintPrior) -> float:
    """How far ``box`` (a footprint), projected into the camera of ``e``, misses the vehicle box that camera saw
    (``silhouette_cost``, the edges the ego's body hides free); inf where ``e`` does not carry its view or where a
    wheel it rests on stands outside ``box`` (by more than ``CONTACT_MARGIN_M``)."""
    if e.cam is None or e.vbox is None:
        return math.inf
    if any(not _holds(box, c, CONTACT_MARGIN_M) for c in e.contacts):
        return math.inf
    vbox = np.asarray(e.vbox, dtype=np.float64)
    size = (box.length, box.width, box.height if box.height > 0 else prior.height * max(1.0, box.length / prior.length))
    pred = silhouette_boxes(e.cam, [[box.x, box.y]], [box.yaw], size, prior.shape)
    return float(silhouette_cost(pred, vbox, hidden=hidden_edges(e.cam, vbox))[0])


def _holds(box: Box3D, xy, margin: float) -> bool:
    """Whether the ground point ``xy`` lies within ``box``'s footprint grown by ``margin`` (m) on every side."""
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    dx, dy = xy[0] - box.x, xy[1] - box.y
    return abs(c * dx + s * dy) <= box.length / 2 + margin and abs(-s * dx + c * dy) <= box.width / 2 + margin


def views_cost(box: Box3D, group: list[Estimate], prior: FootprintPrior) -> float:
    """The worst ``explained_cost`` of ``box`` over the views of ``group``."""
    return max(explained_cost(box, e, prior) for e in group)


def absorb_explained(fused: list[tuple[Box3D, list[Estimate]]],
                     prior: FootprintPrior) -> list[tuple[Box3D, list[Estimate]]]:
    """``fused`` (in ``fuse_frame``'s order: strongest evidence first, then nearest) with each weak footprint
    (``WEAK_EVIDENCE``) that another one explains merged into it: the other's footprint, projected into every camera
    that saw the weak one, draws the box it saw (``explained_cost`` within ``EXPLAINED_COST``), their centres lie
    within ``ABSORB_RADIUS_M`` and they hold no two vehicle boxes of one image. A footprint resting on two wheels
    explains the weak ones it may; between two weak footprints, the one that explains the other's views better than
    the other explains its own. The best-explained pairs merge first; the explaining footprint stays, the absorbed
    estimates join its group."""
    groups = [(box, list(g)) for box, g in fused]
    alive = set(range(len(groups)))
    cost: dict[tuple[int, int], float] = {}   # (i, j): how far i's footprint misses j's views

    def explains(i: int, j: int) -> float:
        if (i, j) not in cost:
            cost[(i, j)] = views_cost(groups[i][0], groups[j][1], prior)
        return cost[(i, j)]

    while True:
        best = None
        for j in alive:
            box, group = groups[j]
            if group[0].evidence not in WEAK_EVIDENCE:
                continue
            for i in alive:
                other, members = groups[i]
                if i == j or math.hypot(other.x - box.x, other.y - box.y) > ABSORB_RADIUS_M:
                    continue
                if members[0].evidence in WEAK_EVIDENCE and not explains(i, j) < explains(j, i):
                    continue
                if any(two_boxes_of_one_image(a, b) for a in group for b in members):
                    continue
                c = explains(i, j)
                if c <= EXPLAINED_COST and (best is None or c < best[0]):
                    best = (c, i, j)
        if best is None:
            break
        _, i, j = best
        groups[i][1].extend(groups[j][1])
        alive.discard(j)
        cost = {k: v for k, v in cost.items() if k[1] != i}   # i's views grew: what explains them is asked again
    return [groups[i] for i in sorted(alive)]


def frame_footprints(views: list[tuple[Record, Camera]], prior: FootprintPrior, radius_m: float,
                     use_relations: bool = True) -> tuple[list[Estimate], list[tuple[Box3D, list[Estimate]]]]:
    """One frame's footprints, as the bev stage scores them and ``deepword infer`` writes them: the estimates of its
    images (``estimate_frame``: the weak ones with their neighbours' axes across the frame's cameras) and their fusion
    (``fuse_frame`` within ``radius_m``, headings by the roles' votes and the prior's heading table; ``use_relations=
    False``, the ``box_bottom`` baseline: neither)."""
    estimates = estimate_frame(views, prior, use_relations)
    return estimates, fuse_frame(estimates, radius_m, prior if use_relations else None)


def footprint_json(box: Box3D, group: list[Estimate]) -> dict:
    """One fused footprint as the bev stage's ``footprints/*.jsonl`` and ``deepword infer``'s ``footprints.jsonl``
    write it: the box, the evidence it rests on, the cameras that saw it, its confidence and where its heading's
    direction came from (``facing``: the detector's facing voted, with any roles and the prior; ``roles``: the wheels'
    roles voted, with the prior; ``axis``: the prior alone, or nothing)."""
    heading_from = ("facing" if any(e.facing_vote for e in group) else
                    "roles" if group_directed(group) else "axis")
    return {**box.to_json(), "evidence": group[0].evidence, "seen_by": sorted({e.camera for e in group}),
            "confidence": round(group_confidence(group), 4), "heading_from": heading_from}


def write_footprints(path, fused: dict[int, list[tuple[Box3D, list[Estimate]]]]) -> None:
    """Fused footprints per frame, one JSON line per frame (``footprint_json`` per footprint): the bev stage's
    ``footprints/<boxes>_<method>.jsonl`` and ``deepword infer``'s ``footprints.jsonl``."""
    with open(path, "w") as fh:
        for frame in sorted(fused):
            fh.write(json.dumps({"frame_id": frame, "footprints": [footprint_json(box, group)
                                                                   for box, group in fused[frame]]}) + "\n")


def seen_cost(cam: Camera, box: Box3D, vbox: np.ndarray, prior: FootprintPrior) -> float:
    """The silhouette cost of ``box`` against the seen vehicle box with every edge counted, hidden or not."""
    pred = silhouette_boxes(cam, [[box.x, box.y]], [box.yaw], _size(prior, box.length / prior.length), prior.shape)
    return float(silhouette_cost(pred, vbox)[0])


def fit_trust(cost: float) -> float:
    """The factor (0-1] a no-wheel estimate's confidence takes from its silhouette fit's cost (``FIT_COST_SCALE``)."""
    return math.exp(-max(0.0, float(cost)) / FIT_COST_SCALE)


# A footprint half under a more confident one keeps a quarter of its confidence, not half: most of the end-to-end
# false positives within 10 m are second footprints of a vehicle another footprint matched (22 of 30 and 135 of 173
# on seed 42's val / train), one- and no-wheel estimates beyond the fusion radius. On three datasets' val and train
# splits, power 2 against 1: AP within 10 m up or level on all six end to end and on labelled boxes, the no-wheel AP
# up on all twelve; 3 gave what 2 gave (docs/bev.md, "Confidence")
OVERLAP_POWER = 2


def suppress_overlaps(fused: list[tuple[Box3D, list[Estimate]]]) -> list[tuple[Box3D, list[Estimate]]]:
    """Soft suppression of a frame's footprints (a Soft-NMS after Bodla et al., 2017, on the ground): two
    vehicles do not overlap on the ground, so a footprint that overlaps a more confident one is more likely a second
    estimate of the same vehicle than another vehicle (an end-on or hidden vehicle's estimate from another camera, off by
    more than the fusion radius). In falling confidence, each footprint's estimates' confidences are multiplied by
    (1 - the share of its area that each more confident footprint covers) ** ``OVERLAP_POWER``. Nothing is removed,
    so a vehicle that another estimate overlaps by mistake keeps its footprint, further down the ranking."""
    order = sorted(range(len(fused)), key=lambda i: -group_confidence(fused[i][1]))
    shapes = [Polygon(box.corners()) for box, _ in fused]
    out = list(fused)
    for k, i in enumerate(order):
        keep = 1.0
        for j in order[:k]:
            smaller = min(shapes[i].area, shapes[j].area)
            if smaller > 0:
                keep *= (1.0 - min(1.0, shapes[i].intersection(shapes[j]).area / smaller)) ** OVERLAP_POWER
        if keep < 1.0:
            box, group = out[i]
            out[i] = (box, [replace(e, confidence=e.confidence * keep) for e in group])
    return out


def group_confidence(group: list[Estimate]) -> float:
    """A fused footprint's confidence: the highest of its estimates'."""
    return max(e.confidence for e in group)


def group_directed(group: list[Estimate]) -> bool:
    """Whether a fused footprint's heading points to the front (one of its estimates is directed)."""
    return any(e.directed for e in group)


def group_wheels(group: list[Estimate]) -> int:
    """Wheels (0, 1, 2 = two or more) the fused footprint's strongest evidence rests on."""
    return EVIDENCE_WHEELS[group[0].evidence]


# --- fitting the prior on 3D truth ------------------------------------------------------------------------

def fit_prior(samples) -> FootprintPrior:
    """Fit ``FootprintPrior`` from (record, camera, vehicles {box_id: Box3D}, wheels {box_id: (x, y)})
    tuples of train images with ground-truth boxes and relations."""
    widths, lengths, heights, bases, insets, shifts, box_shifts = [], [], [], [], [], [], []
    seen_vehicles, unique = set(), []
    for rec, cam, vehicles, wheels in samples:
        owner = rec.owner_of()
        by_id = {int(b): rec.boxes[i] for i, b in enumerate(rec.box_ids)}
        for vid, v in vehicles.items():
            key = (rec.frame_id, round(v.x, 2), round(v.y, 2))
            if key in seen_vehicles:
                continue
            seen_vehicles.add(key)
            unique.append(v)
            widths.append(v.width)
            lengths.append(v.length)
            heights.append(v.height)
            u = np.array([math.cos(v.yaw), math.sin(v.yaw)])
            n = np.array([-u[1], u[0]])
            for w, owner_id in owner.items():
                if owner_id == vid and w in wheels:
                    insets.append(v.width / 2 - abs(float(np.dot(np.array(wheels[w]) - (v.x, v.y), n))))
        for a, b in rec.wheel_pairs:
            if a in wheels and b in wheels and owner.get(a) == owner.get(b) and owner.get(a) in vehicles:
                v = vehicles[owner[a]]
                bases.append((float(np.linalg.norm(np.subtract(wheels[a], wheels[b]))), v.length))
        wids = [w for w in wheels if w in by_id]
        if wids:
            xy, ok = wheel_contacts(cam, np.array([by_id[w][:4] for w in wids]), None)
            cam_xy = cam.translation[:2]
            for i, w in enumerate(wids):
                if ok[i]:
                    seen = float(np.linalg.norm(xy[i] - cam_xy))
                    shifts.append((seen, float(np.linalg.norm(np.subtract(wheels[w], cam_xy))) - seen))
        vids = [v for v in vehicles if v in by_id]
        if vids:
            xy, ok = box_bottom_points(cam, np.array([by_id[v][:4] for v in vids]))
            for i, v in enumerate(vids):
                if ok[i]:
                    c = np.array([vehicles[v].x, vehicles[v].y])
                    box_shifts.append(np.linalg.norm(c - cam.translation[:2]) - np.linalg.norm(xy[i] - cam.translation[:2]))
    if len(bases) < 2 or not widths:
        raise ValueError("the train split holds too little 3D truth to fit a footprint prior "
                         f"({len(widths)} vehicles, {len(bases)} visible couples)")
    wb = np.array(bases)
    slope, offset = np.polyfit(wb[:, 0], wb[:, 1], 1)
    contact_shift, contact_slope = fit_contact_shift(shifts)
    return FootprintPrior(width=float(np.median(widths)), length=float(np.median(lengths)),
                          wheelbase=float(np.median(wb[:, 0])), length_slope=float(slope), length_offset=float(offset),
                          track_inset=float(np.median(insets)) if insets else 0.0,
                          contact_shift=contact_shift, contact_slope=contact_slope,
                          box_shift=float(np.median(box_shifts)) if box_shifts else 0.0,
                          height=float(np.median(heights)), heading=fit_heading(unique))


# fewer wheels than this fit the contact shift as one median (no slope): a line needs wheels at many distances
MIN_SLOPE_WHEELS = 50


def fit_contact_shift(shifts: list[tuple[float, float]]) -> tuple[float, float]:
    """(``contact_shift``, ``contact_slope``): the median line of the contact shift over the back-projected distance,
    from (distance, true distance - that distance) per train wheel; a median regression (``QuantileRegressor`` at
    0.5), as robust to a badly drawn box as the single median it extends. On the generator's train split the shift is
    0.12 m at 1.5 m from the camera, 0.35 m at 8.5 and 0.71 m at 20: one median (0.31 m) put two-wheel footprints
    within 10 m ~0.1 m too far from the camera and those beyond 15 m 0.3 m too near (docs/bev.md, "Wheel contacts")."""
    if not shifts:
        return 0.0, 0.0
    a = np.asarray(shifts, dtype=np.float64)
    if len(a) < MIN_SLOPE_WHEELS:
        return float(np.median(a[:, 1])), 0.0
    from sklearn.linear_model import QuantileRegressor  # imported here: deepword infer never fits a prior

    line = QuantileRegressor(quantile=0.5, alpha=0.0, solver="highs").fit(a[:, :1], a[:, 1])
    return float(line.intercept_), float(line.coef_[0])
