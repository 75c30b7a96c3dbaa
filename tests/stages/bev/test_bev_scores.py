"""The bev stage's nuScenes-style detection scores: AP 100 for perfect footprints, a hand-computed AP for a crafted
precision-recall curve, headings over 360 deg against modulo 180 deg (and wheel roles that set the direction),
confidences, subsets (wheel populations, distance bins) and the MLflow key names."""

import math

import numpy as np
import pytest
from omegaconf import OmegaConf

from deepword.footprint import (
    FIT_COST_SCALE,
    ROLE_WHEEL_LOGIT,
    Estimate,
    fit_trust,
    footprints_from_contacts,
    fuse_frame,
    group_confidence,
    suppress_overlaps,
)
from deepword.format_3d import Box3D
from stages.bev.metrics import (
    DIST_THRESHOLDS,
    Scored,
    TrueVehicle,
    average_precision,
    detection_scores,
    recall_at_precision,
    scale_error,
    summarise,
)
from stages.bev.stage import detection_subsets, flatten
from tests.stages.bev.test_bev import PRIOR, _camera, _contacts, _record

BCFG = OmegaConf.create({"max_range_m": 10.0, "range_bins": [[0, 5], [5, 10], [10, 20]]})
ALL = (lambda t: True, lambda e: True)


def _car(x, y, yaw=0.0):
    return Box3D(x, y, 4.5, 1.8, yaw, 1.5)


def test_perfect_footprints_score_ap_100_and_zero_errors():
    frames = []
    for f in range(3):
        cars = [_car(4.0 + f, 2.5), _car(-6.0, -3.0 - f, 0.4), _car(12.0, 1.0, -2.0)]
        frames.append(([TrueVehicle(c) for c in cars], [Scored(c, 0.5 + 0.1 * i) for i, c in enumerate(cars)]))
    s = detection_scores(frames, *ALL)
    assert s["ap"] == pytest.approx(100) and all(s[f"ap_{k}m"] == pytest.approx(100) for k in ("0p5", "1", "2", "4"))
    assert s["ate_m"] == pytest.approx(0) and s["ase"] == pytest.approx(0) and s["aoe_deg"] == pytest.approx(0)
    assert s["iou"] == pytest.approx(1) and s["recall"] == 100 and s["precision"] == 100 and s["vehicles"] == 9
    assert average_precision(np.ones(101)) == pytest.approx(1.0)


def test_a_crafted_precision_recall_curve_gives_the_hand_computed_ap():
    """Two true vehicles; ranked: a false positive (0.9), then both true ones (0.8, 0.7). Recall 0, 1/2, 1 with
    precision 0, 1/2, 2/3: sampled at the 101 recall levels, p(r) = r up to 1/2, then 1/2 + (r - 1/2)/3.
    AP = mean over r = 0.11 .. 1.00 of (p - 0.1)/0.9 = (8.2 + 24.25) / 90 / 0.9 = 40.06 %."""
    a, b = _car(5.0, 0.0), _car(-5.0, 3.0)
    frames = [([TrueVehicle(a), TrueVehicle(b)],
               [Scored(_car(0.0, -8.0), 0.9), Scored(a, 0.8), Scored(b, 0.7)])]
    s = detection_scores(frames, *ALL)
    expected = 100 * (8.2 + 24.25) / 90 / 0.9
    for t in DIST_THRESHOLDS:
        assert s[f"ap_{t:g}m".replace(".", "p")] == pytest.approx(expected, abs=1e-9)
    assert s["recall"] == 100 and s["precision"] == pytest.approx(200 / 3)
    # the false positive ranked last: precision 1 up to recall 1, where the curve ends at 2/3 (nuScenes reads the
    # last point of a recall level), so only the level r = 1.00 loses (1 - 2/3) / 0.9
    frames[0][1][0] = Scored(_car(0.0, -8.0), 0.1)
    assert detection_scores(frames, *ALL)["ap"] == pytest.approx(100 - 100 * (1 / 3) / 90 / 0.9)


def test_recall_at_95_percent_precision_is_read_where_a_threshold_can_cut():
    """Twenty true vehicles; ranked: 19 true, then a false one, then one true. Keeping the first 19 is 100 % precise
    (recall 95 %), the first 20 95 % (still recall 95 %), all 21 20/21 = 95.2 % (recall 100 %)."""
    tp = np.array([1] * 19 + [0, 1])
    conf = np.linspace(1.0, 0.5, 21)
    assert recall_at_precision(tp, conf, 20, 0.95) == pytest.approx(1.0)
    # two false ones: all 22 keep 20/22 = 90.9 %, so the threshold stops after the 19 true ones
    tp2, conf2 = np.array([1] * 19 + [0, 0, 1]), np.linspace(1.0, 0.5, 22)
    assert recall_at_precision(tp2, conf2, 20, 0.95) == pytest.approx(0.95)
    # a tie cannot be cut: the false estimate shares the 10th true one's confidence, so keeping the 10th keeps it
    tp3 = np.array([1] * 9 + [1, 0] + [0] * 5)
    conf3 = np.array([1.0 - 0.01 * i for i in range(9)] + [0.5, 0.5] + [0.1] * 5)
    assert recall_at_precision(tp3, conf3, 10, 0.95) == pytest.approx(0.9)
    assert recall_at_precision(np.array([0, 1]), np.array([0.9, 0.8]), 1, 0.95) == 0.0
    # in the scores: the crafted curve above never reaches 95 % precision past its first estimate (a false one)
    a, b = _car(5.0, 0.0), _car(-5.0, 3.0)
    frames = [([TrueVehicle(a), TrueVehicle(b)], [Scored(_car(0.0, -8.0), 0.9), Scored(a, 0.8), Scored(b, 0.7)])]
    assert detection_scores(frames, *ALL)["recall_at_p95"] == 0.0
    frames[0][1][0] = Scored(_car(0.0, -8.0), 0.1)
    assert detection_scores(frames, *ALL)["recall_at_p95"] == 100.0


def test_ap_per_threshold_follows_the_centre_distance():
    t = _car(6.0, 2.0)
    frames = [([TrueVehicle(t)], [Scored(_car(6.0, 2.0 + 1.5), 1.0)])]   # 1.5 m off: a hit at 2 and 4 m only
    s = detection_scores(frames, *ALL)
    assert (s["ap_0p5m"], s["ap_1m"], s["ap_2m"], s["ap_4m"]) == (0, 0, pytest.approx(100), pytest.approx(100))
    assert s["ap"] == pytest.approx(50) and s["ate_m"] == pytest.approx(1.5)
    # three matches 0.1, 0.2 and 1.5 m off, ranked best first: the median is the middle one, the ATE (the running
    # mean read at the recall levels) leans towards the first
    u, v = _car(-6.0, 3.0), _car(0.0, -7.0)
    frames = [([TrueVehicle(t), TrueVehicle(u), TrueVehicle(v)],
               [Scored(_car(6.1, 2.0), 0.9), Scored(_car(-6.0, 3.2), 0.8), Scored(_car(0.0, -5.5), 0.7)])]
    s = detection_scores(frames, *ALL)
    assert s["center_err_median_m"] == pytest.approx(0.2) and s["ate_m"] < (0.1 + 0.2 + 1.5) / 3


def test_headings_over_360_deg_tell_front_from_back_and_modulo_180_do_not():
    t = _car(5.0, 1.0, 0.3)
    for turn, aoe, aoe180 in ((math.pi, 180.0, 0.0), (math.pi / 2, 90.0, 90.0), (0.1, math.degrees(0.1),
                                                                                  math.degrees(0.1))):
        s = detection_scores([([TrueVehicle(t)], [Scored(_car(5.0, 1.0, 0.3 + turn), 1.0)])], *ALL)
        assert s["aoe_deg"] == pytest.approx(aoe) and s["aoe180_deg"] == pytest.approx(aoe180, abs=1e-9)
        assert s["aoe_rad"] == pytest.approx(math.radians(aoe))
    # the paired medians stay modulo 180 deg
    from stages.bev.metrics import match_frame
    assert summarise(match_frame([TrueVehicle(t)], [_car(5.0, 1.0, 0.3 + math.pi)], 2.0))["heading_err_deg"] == \
        pytest.approx(0, abs=1e-9)
    # ASE: sizes only (1 - IoU of the aligned boxes)
    assert scale_error(t, Box3D(9.0, 9.0, 4.5, 0.9, 2.0, 1.5)) == pytest.approx(0.5)


def test_wheel_roles_point_the_heading_to_the_front():
    cam = _camera()
    v = Box3D(-1.2, 4.6, 4.5, 1.8, 0.08)
    c = _contacts(v)
    contacts = {2: c["rr"], 3: c["fr"]}
    # a couple listed front first: without roles the axis only (heading backwards), with roles the front
    no_roles = _record(cam, [(0, 2, None), (0, 3, None)], [(3, 2)], n_vehicles=2, n_wheels=2)
    e = footprints_from_contacts(no_roles, cam, PRIOR, contacts)[0]
    assert e.evidence == "side" and not e.directed and abs(math.remainder(e.box.yaw - v.yaw, 2 * math.pi)) > 3
    roles = _record(cam, [(0, 2, "rear"), (0, 3, "front")], [(3, 2)], n_vehicles=2, n_wheels=2)
    e = footprints_from_contacts(roles, cam, PRIOR, contacts)[0]
    assert e.directed and math.remainder(e.box.yaw - v.yaw, 2 * math.pi) == pytest.approx(0, abs=1e-9)
    # one axle: its role says whether the body extends back (rear axle seen) or forward (front axle seen)
    front_cam = _camera(yaw=0.0, position=(3.7, 0.0, 0.66))
    ahead = Box3D(9.0, 0.3, 4.5, 1.8, 0.05)
    ca = _contacts(ahead)
    for role, turn in (("rear", 0.0), ("front", math.pi)):
        rec = _record(front_cam, [(0, 1, role), (0, 2, role)], [], n_vehicles=1, n_wheels=2, camera="front")
        e = footprints_from_contacts(rec, front_cam, PRIOR, {1: ca["rl"], 2: ca["rr"]})[0]
        assert e.evidence == "axle" and e.directed
        assert abs(math.remainder(e.box.yaw - ahead.yaw - turn, 2 * math.pi)) < 1e-6


def test_confidence_follows_evidence_and_box_scores_and_fusion_keeps_the_direction():
    cam = _camera()
    v = Box3D(-1.2, 4.6, 4.5, 1.8, 0.08)
    c = _contacts(v)
    rec = _record(cam, [(0, 2, "rear"), (0, 3, "front")], [(2, 3)], n_vehicles=2, n_wheels=2)
    rec.boxes[0, 4], rec.boxes[2, 4], rec.boxes[3, 4] = 0.8, 0.5, 0.7
    est = footprints_from_contacts(rec, cam, PRIOR, {2: c["rr"], 3: c["fr"]})
    side, box = est
    assert (side.evidence, box.evidence) == ("side", "box")
    assert side.confidence == pytest.approx(0.9 * 0.8 * 0.6)
    assert 0 < box.confidence < 0.3   # 0.3 x its box score 1 x how well its silhouette fits the box (fit_trust)
    # an undirected estimate of the same vehicle turned backwards, fused with a weaker directed one: the front wins
    back = Estimate(Box3D(v.x, v.y, 4.5, 1.8, v.yaw + math.pi), "sides", "front", 0, "a.png", 0.95)
    wheel = Estimate(Box3D(v.x + 0.2, v.y, 4.5, 1.8, v.yaw + 0.1), "wheel", "left", 0, "b.png", 0.5,
                     role_vote=ROLE_WHEEL_LOGIT)
    (fused, group), = fuse_frame([wheel, back], 1.5)
    assert abs(math.remainder(fused.yaw - v.yaw, 2 * math.pi)) < 1e-9 and group_confidence(group) == 0.95


def test_fit_trust_falls_with_the_fit_cost():
    costs = [0.0, 0.01, 0.1, 1.0]
    trust = [fit_trust(c) for c in costs]
    assert trust[0] == 1.0 and all(a > b > 0 for a, b in zip(trust[:-1], trust[1:], strict=True))
    assert fit_trust(FIT_COST_SCALE) == pytest.approx(math.exp(-1))


def test_overlapping_footprints_keep_the_square_of_their_uncovered_share_of_their_confidence():
    """Two vehicles do not overlap on the ground: a footprint half under a more confident one keeps a quarter of its
    confidence ((1/2)^2, OVERLAP_POWER), one a quarter under each of two keeps (3/4)^2 x (3/4)^2, one clear of the
    others all of it; the most confident keeps its own whatever lies under it, and nothing is removed."""
    def est(x, y, conf, length=4.0):
        return Estimate(Box3D(x, y, length, 2.0, 0.0), "box", "front", 0, "a.png", conf)

    strong = (est(0.0, 0.0, 0.9).box, [est(0.0, 0.0, 0.9), est(0.1, 0.0, 0.5)])
    half = (est(2.0, 0.0, 0.3).box, [est(2.0, 0.0, 0.3)])            # its rear half under `strong`
    clear = (est(0.0, 5.0, 0.4).box, [est(0.0, 5.0, 0.4)])
    out = suppress_overlaps([half, strong, clear])
    assert [len(g) for _, g in out] == [1, 2, 1] and [b for b, _ in out] == [half[0], strong[0], clear[0]]
    assert group_confidence(out[1][1]) == 0.9 and group_confidence(out[2][1]) == 0.4
    assert group_confidence(out[0][1]) == pytest.approx(0.3 * 0.5 ** 2)
    left, right = (est(-3.0, 0.0, 0.8).box, [est(-3.0, 0.0, 0.8)]), (est(3.0, 0.0, 0.7).box, [est(3.0, 0.0, 0.7)])
    middle = (est(0.0, 0.0, 0.2).box, [est(0.0, 0.0, 0.2)])          # a quarter under each neighbour
    out = suppress_overlaps([left, middle, right])
    assert group_confidence(out[1][1]) == pytest.approx(0.2 * 0.75 ** 2 * 0.75 ** 2)
    assert [group_confidence(g) for _, g in suppress_overlaps([clear])] == [0.4]


def test_subsets_bins_and_populations():
    near = TrueVehicle(_car(3.0, 0.0), wheels=2)      # 0-5 m, two wheels
    mid = TrueVehicle(_car(0.0, 7.0), wheels=1)       # 5-10 m, one wheel
    none = TrueVehicle(_car(-8.0, 0.0), wheels=0)     # 5-10 m, no wheel
    far = TrueVehicle(_car(15.0, 0.0), wheels=2)      # 10-20 m: outside every population
    ests = [Scored(near.box, 0.9, 2), Scored(mid.box, 0.8, 1), Scored(_car(0.0, -3.5), 0.7, 0),   # a false one at 3.5 m
            Scored(_car(14.0, 6.0), 0.6, 2)]                                                     # a false one at 15.2 m
    frames = [([near, mid, none, far], ests)]
    subsets = detection_subsets(BCFG)
    assert list(subsets) == ["all", "two_wheels", "one_wheel", "no_wheel", "0-5m", "5-10m", "10-20m"]
    s = {name: detection_scores(frames, *keep) for name, keep in subsets.items()}
    assert [s[n]["vehicles"] for n in subsets] == [3, 1, 1, 1, 1, 2, 1]
    assert s["all"]["recall"] == pytest.approx(200 / 3) and s["all"]["precision"] == pytest.approx(200 / 3)
    # the false positive within range counts in every wheel population; estimates matched elsewhere in none
    assert s["two_wheels"]["estimates"] == 2 and s["two_wheels"]["precision"] == 50
    assert s["no_wheel"]["recall"] == 0 and s["no_wheel"]["ap"] == 0
    assert s["0-5m"]["estimates"] == 2 and s["5-10m"]["recall"] == 50 and s["5-10m"]["precision"] == 100
    assert s["10-20m"]["recall"] == 0 and s["10-20m"]["estimates"] == 1


def test_metric_names():
    frames = [([TrueVehicle(_car(3.0, 1.0), paired=True, wheels=2)], [Scored(_car(3.0, 1.0), 1.0, 2)])]
    detection = {"detected": {"deepword_then_logic": {n: detection_scores(frames, *k)
                                                      for n, k in detection_subsets(BCFG).items()}}}
    from stages.bev.metrics import match_frame
    medians = {"detected": {"deepword_then_logic": {"": summarise(match_frame(frames[0][0], [frames[0][1][0].box], 2.0)),
                                                    "paired": summarise(match_frame(frames[0][0], [frames[0][1][0].box],
                                                                                    2.0))}}}
    keys = flatten(medians, detection)
    p = "bev.detected.deepword_then_logic."
    for k in ("all.ap", "all.ap_0p5m", "all.ap_1m", "all.ap_2m", "all.ap_4m", "all.ate_m", "all.ase", "all.aoe_rad",
              "all.aoe_deg", "all.aoe180_deg", "all.iou", "all.recall", "all.precision", "two_wheels.ate_m",
              "0-5m.recall", "center_err_m", "heading_err_deg", "bev_iou", "recall", "paired.center_err_m"):
        assert p + k in keys, k
    assert keys[p + "all.ap"] == pytest.approx(100) and p + "one_wheel.ap" not in keys   # no vehicles: no key
