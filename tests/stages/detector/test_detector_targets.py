import math

import numpy as np
import pytest

from stages.detector.targets import (
    TTFNET_BETA,
    centernet_targets,
    draw_gaussian,
    gaussian2d,
    gaussian_radius,
    ttfnet_box_targets,
)


def test_gaussian_radius_known_values():
    # CenterNet's released rule: the third case with root (b3 + sqrt(b3^2 - 4 a3 c3)) / 2, o = 0.7.
    # 10 x 10: (-2*0.7*20 + sqrt((0.7*2*20)^2 + 16*0.7*0.3*100)) / 2 = (-28 + sqrt(1120)) / 2
    assert gaussian_radius(10, 10) == pytest.approx((-28 + math.sqrt(1120)) / 2)
    assert gaussian_radius(10, 10) == pytest.approx(2.7332, abs=1e-4)
    # 8 x 4: (-16.8 + sqrt(16.8^2 + 16*0.7*0.3*32)) / 2
    assert gaussian_radius(8, 4) == pytest.approx(1.4711, abs=1e-4)
    assert gaussian_radius(4, 8) == gaussian_radius(8, 4)
    # a looser overlap gives a larger radius; radius grows with the object
    assert gaussian_radius(10, 10, 0.5) > gaussian_radius(10, 10, 0.7)
    assert gaussian_radius(40, 40) == pytest.approx(4 * gaussian_radius(10, 10))


def test_draw_gaussian_peak_shape_and_borders():
    hm = np.zeros((9, 9), dtype=np.float32)
    draw_gaussian(hm, (4, 4), 2)
    sigma = 5 / 6
    assert hm[4, 4] == 1.0
    assert hm[4, 5] == pytest.approx(math.exp(-1 / (2 * sigma ** 2)), rel=1e-5)
    assert hm[3, 3] == pytest.approx(math.exp(-2 / (2 * sigma ** 2)), rel=1e-5)
    assert hm[4, 7] == 0.0 and hm.sum() == pytest.approx(gaussian2d(5, sigma).sum(), rel=1e-5)
    # at a corner the Gaussian is cut, not wrapped, and an existing larger value is kept (max)
    hm2 = np.zeros((5, 5), dtype=np.float32)
    hm2[1, 1] = 0.99
    draw_gaussian(hm2, (0, 0), 2)
    assert hm2[0, 0] == 1.0 and hm2[1, 1] == 0.99 and hm2[4, 4] == 0.0


def test_centernet_targets_indices_sizes_offsets():
    boxes = np.array([[2.0, 3.0, 6.0, 5.5], [10.2, 1.0, 11.8, 2.6]])
    t = centernet_targets(boxes, np.array([0, 1]), num_classes=2, out_width=16, out_height=8, max_objects=4)
    assert t["hm"].shape == (2, 8, 16) and t["mask"].tolist() == [1, 1, 0, 0]
    # centre (4, 4.25) -> cell (4, 4), offset (0, 0.25), flat index 4 * 16 + 4
    assert t["ind"][0] == 4 * 16 + 4 and np.allclose(t["reg"][0], [0, 0.25]) and np.allclose(t["wh"][0], [4, 2.5])
    assert t["hm"][0, 4, 4] == 1.0 and t["hm"][1, 1, 11] == 1.0
    assert t["hm"][1].max() == 1.0 and t["hm"][0, 1, 11] < 1.0  # classes drawn on their own channel
    with pytest.raises(ValueError, match="max_objects"):
        centernet_targets(boxes, np.array([0, 1]), 2, 16, 8, max_objects=1)


def test_ttfnet_box_targets_sample_the_central_share_of_each_box():
    # stride 4, a 64 x 32 px box centred on cell (8, 6) and a 12 x 12 px one on cell (3, 2), apart
    boxes = np.array([[2.0, 10.0, 66.0, 42.0], [8.0, 4.0, 20.0, 16.0]])
    t = ttfnet_box_targets(boxes, out_width=20, out_height=12, down_ratio=4)
    weight, box = t["box_weight"], t["box"]
    ys, xs = np.nonzero(weight)
    big = np.all(box[:, ys, xs].T == boxes[0], axis=1)
    # the big box's cells: within beta x its half-sides of its centre cell (16 x 8 cells -> radii 4 x 2)
    assert np.abs(xs[big] - 8).max() == int(TTFNET_BETA * 16 / 2) and np.abs(ys[big] - 6).max() == int(TTFNET_BETA * 8 / 2)
    # each object's weights sum to log(its area): big and small boxes count alike, not by their cell counts
    assert weight[ys[big], xs[big]].sum() == pytest.approx(math.log(64 * 32), rel=1e-5)
    assert weight[ys[~big], xs[~big]].sum() == pytest.approx(math.log(12 * 12), rel=1e-5)
    assert (~big).sum() == 1 and big.sum() > 20   # a 3-cell box regresses from its centre cell only
    assert weight[6, 8] == weight[ys[big], xs[big]].max()   # the centre weighs most


def test_ttfnet_box_targets_smaller_box_wins_overlaps_and_boxes_are_clipped():
    boxes = np.array([[0.0, 0.0, 80.0, 48.0], [28.0, 16.0, 52.0, 32.0], [70.0, -8.0, 100.0, 20.0]])
    t = ttfnet_box_targets(boxes, out_width=20, out_height=12, down_ratio=4)
    assert np.allclose(t["box"][:, 6, 10], [28.0, 16.0, 52.0, 32.0])   # the small box's centre cell
    ys, xs = np.nonzero(t["box_weight"])
    targets = t["box"][:, ys, xs]
    assert targets[1].min() >= 0 and targets[2].max() <= 80   # the third box clipped to the 80 x 48 input
