"""Long vehicles (buses) with the in-domain, car-sized prior: a one-wheel or no-wheel vehicle whose box is a long
vehicle's image comes out long, a car's stays car-sized, and the short estimates that cameras make of one long
vehicle's ends fuse with its long footprint, while a neighbouring car stays a car of its own."""

import math

import numpy as np

from deepword.footprint import (
    SIZE_REFINE_STEP,
    SIZE_SCALES,
    Estimate,
    _size,
    box_bottom_estimate,
    fit_free,
    fit_sized,
    fit_wheel,
    fuse_frame,
    same_vehicle,
    shared_fits,
    silhouette_boxes,
)
from deepword.format_3d import Box3D
from tests.stages.bev.test_bev import PRIOR, _camera


def _seen(cam, v: Box3D, scale: float) -> np.ndarray:
    return np.r_[silhouette_boxes(cam, [[v.x, v.y]], [v.yaw], _size(PRIOR, scale), PRIOR.shape)[0], 1.0, 0, 0]


def _contact(v: Box3D, scale: float) -> np.ndarray:
    """The rear right wheel's contact of ``v`` (a vehicle of the prior's shape at ``scale``)."""
    u = np.array([math.cos(v.yaw), math.sin(v.yaw)])
    n = np.array([-u[1], u[0]])
    lateral = _size(PRIOR, scale)[1] / 2 - PRIOR.track_inset
    return np.array([v.x, v.y]) - u * PRIOR.wheelbase * scale / 2 - n * lateral


def test_one_wheel_of_a_long_vehicle_gives_a_long_footprint():
    cam = _camera()   # the left camera
    scale = SIZE_SCALES[2]
    bus = Box3D(0.5, 5.5, PRIOR.length * scale, 0.0, 0.05)
    vbox = _seen(cam, bus, scale)
    box, _ = fit_sized(fit_wheel, cam, _contact(bus, scale), None, vbox, PRIOR, [bus.yaw])
    # the size's refinement may settle one step shorter (SIZE_PENALTY: a longer size must fit better, and a step
    # shorter fits this noise-free silhouette almost as well): within a step of the bus's length, placed within 0.2 m
    assert abs(box.length - bus.length) <= SIZE_REFINE_STEP * PRIOR.length + 1e-6
    assert math.hypot(box.x - bus.x, box.y - bus.y) < 0.2
    car_size, _ = fit_wheel(cam, _contact(bus, scale), None, vbox, PRIOR, [bus.yaw])   # the prior's size alone
    assert car_size.length == PRIOR.length and math.hypot(car_size.x - bus.x, car_size.y - bus.y) > 1.0


def test_a_cars_box_keeps_the_priors_size():
    cam = _camera()
    car = Box3D(0.5, 5.5, PRIOR.length, PRIOR.width, 0.05)
    vbox = _seen(cam, car, 1.0)
    box, _ = fit_sized(fit_free, cam, vbox, PRIOR, box_bottom_estimate(cam, vbox, PRIOR), [car.yaw])
    assert box.length == PRIOR.length
    box, _ = fit_sized(fit_wheel, cam, _contact(car, 1.0), None, vbox, PRIOR, [car.yaw])
    assert box.length == PRIOR.length and math.hypot(box.x - car.x, box.y - car.y) < 0.1


def test_shared_fits_compute_a_fit_once_per_inputs_and_give_the_same_answer():
    cam = _camera()
    car = Box3D(0.5, 5.5, PRIOR.length, PRIOR.width, 0.05)
    vbox = _seen(cam, car, 1.0)
    calls = []

    def counted(*args, scale):
        calls.append(scale)
        return fit_wheel(*args, scale=scale)

    counted.__name__ = "fit_wheel"
    alone = fit_sized(counted, cam, _contact(car, 1.0), None, vbox, PRIOR, [car.yaw])
    per_fit = len(SIZE_SCALES) + 1   # the coarse sizes, then the best one's (1.0) longer neighbour
    assert calls == [*SIZE_SCALES, 1.0 + SIZE_REFINE_STEP]
    with shared_fits():
        first = fit_sized(counted, cam, _contact(car, 1.0), None, vbox, PRIOR, [car.yaw])
        again = fit_sized(counted, cam, _contact(car, 1.0).copy(), None, vbox.copy(), PRIOR, [car.yaw])
        assert len(calls) == 2 * per_fit, "the same inputs (equal arrays): fitted once"
        fit_sized(counted, cam, _contact(car, 1.0), None, vbox, PRIOR, [car.yaw + 0.1])
        assert len(calls) == 3 * per_fit, "another axis: fitted again"
    assert alone == first == again
    fit_sized(counted, cam, _contact(car, 1.0), None, vbox, PRIOR, [car.yaw])
    assert len(calls) == 4 * per_fit, "outside shared_fits nothing is remembered"


def _est(box: Box3D, evidence: str, camera: str) -> Estimate:
    return Estimate(box=box, evidence=evidence, camera=camera, vehicle_box_id=0, image=camera)


def test_short_estimates_of_a_long_vehicles_ends_fuse_with_it():
    bus = Box3D(0.0, 6.0, 9.0, 2.4, 0.0)
    # the front and rear cameras each see one end and place a car-sized footprint there, 2.2 m from the bus's centre
    ends = [Box3D(bus.x + s * (bus.length - PRIOR.length) / 2, bus.y, PRIOR.length, PRIOR.width, 0.0) for s in (1, -1)]
    est = [_est(bus, "side", "left"), _est(ends[0], "wheel", "front"), _est(ends[1], "box", "rear")]
    assert all(math.hypot(e.x - bus.x, e.y - bus.y) > 1.5 for e in ends)
    fused = fuse_frame(est, radius_m=1.5)
    assert len(fused) == 1 and fused[0][0] == bus
    # a car parked 2.6 m beside the bus (not past its end) stays a vehicle of its own
    beside = Box3D(bus.x, bus.y + 2.6, PRIOR.length, PRIOR.width, 0.0)
    assert not same_vehicle(bus, beside, 1.5)
    assert len(fuse_frame([*est, _est(beside, "wheel", "right")], radius_m=1.5)) == 2
    # two car-sized estimates: the plain radius
    car = Box3D(0.0, 6.0, PRIOR.length, PRIOR.width, 0.0)
    assert not same_vehicle(car, Box3D(2.2, 6.0, PRIOR.length, PRIOR.width, 0.0), 1.5)
