"""Which way a footprint faces: the heading prior fitted from where vehicles stand, the roles' weak votes (a couple's
listed order included), their sum over a frame's cameras in the fusion, and AOE over tied confidences."""

import math
from dataclasses import replace

import numpy as np
import pytest

from deepword.footprint import (
    ROLE_COUPLE_LOGIT,
    ROLE_WHEEL_LOGIT,
    Estimate,
    FootprintPrior,
    fit_heading,
    footprints_from_contacts,
    fuse_frame,
    heading_prior_logit,
)
from deepword.format_3d import Box3D
from stages.bev.metrics import Scored, TrueVehicle, detection_scores
from tests.stages.bev.test_bev import PRIOR, _camera, _contacts, _record


def _yaw_err(a: float, b: float) -> float:
    return abs(math.degrees(math.remainder(a - b, 2 * math.pi)))


def _lane_prior(share_ahead: float = 0.9) -> FootprintPrior:
    """Vehicles ahead and behind along x: ``share_ahead`` of them face +x; across the ego on its left, all face -y."""
    n = 40
    along = [Box3D(6.0 + (k % 4), 0.5, 4.5, 1.8, 0.0 if k < share_ahead * n else math.pi) for k in range(n)]
    across = [Box3D(1.0 + (k % 3), 6.5, 4.5, 1.8, -math.pi / 2) for k in range(10)]
    return replace(PRIOR, heading=fit_heading(along + across))


def test_heading_prior_follows_where_train_vehicles_face():
    prior = _lane_prior(0.9)
    ahead = Box3D(7.0, 0.5, 4.5, 1.8, 0.02)
    assert heading_prior_logit(prior, ahead) > 1.0                                     # +x: the way most face here
    assert heading_prior_logit(prior, replace(ahead, yaw=math.pi + 0.02)) == pytest.approx(
        -heading_prior_logit(prior, ahead))
    beside = Box3D(2.0, 6.5, 4.5, 1.8, math.pi / 2)                                    # across: all faced -y
    assert heading_prior_logit(prior, beside) < -1.0 < 1.0 < heading_prior_logit(prior, replace(beside, yaw=-math.pi / 2))
    # a cell no train vehicle stood in takes its axis class's share; an even class gives no preference
    far = Box3D(-14.0, -9.0, 4.5, 1.8, 0.0)
    assert heading_prior_logit(prior, far) == pytest.approx(math.log(prior.heading["1"] / (1 - prior.heading["1"])))
    assert heading_prior_logit(replace(PRIOR, heading=None), ahead) == 0.0
    # the table survives the prior's JSON
    again = FootprintPrior.from_json(prior.to_json())
    assert heading_prior_logit(again, ahead) == pytest.approx(heading_prior_logit(prior, ahead), abs=1e-3)
    assert FootprintPrior.from_json(PRIOR.to_json()).heading is None


def test_fusion_sums_the_cameras_role_votes_and_the_prior():
    truth = Box3D(7.0, 0.5, 4.5, 1.8, 0.0)
    backwards = replace(truth, yaw=math.pi)
    bare = Estimate(backwards, "side", "front", 0, "f.png", 0.9)
    # nothing votes: the estimate's own heading stays
    (box, _), = fuse_frame([bare], 1.5)
    assert _yaw_err(box.yaw, math.pi) < 1e-9
    # the prior turns it the way vehicles there face
    (box, _), = fuse_frame([bare], 1.5, _lane_prior(0.9))
    assert _yaw_err(box.yaw, truth.yaw) < 1e-9
    # one weak role vote against the prior loses; with an even prior, it wins
    voted = replace(bare, role_vote=ROLE_COUPLE_LOGIT)                 # roles: "backwards" is the front
    (box, _), = fuse_frame([voted], 1.5, _lane_prior(0.9))
    assert _yaw_err(box.yaw, truth.yaw) < 1e-9
    (box, _), = fuse_frame([voted], 1.5, _lane_prior(0.5))
    assert _yaw_err(box.yaw, math.pi) < 1e-9
    # two cameras' votes for the truth, one of them on the other axis direction, add up
    other = Estimate(replace(truth, x=7.2, yaw=0.05), "wheel", "left", 3, "l.png", 0.5, role_vote=ROLE_WHEEL_LOGIT)
    (box, group), = fuse_frame([voted, other, replace(bare, camera="right", image="r.png", role_vote=-ROLE_COUPLE_LOGIT)],
                               1.5, _lane_prior(0.5))
    assert len(group) == 3 and _yaw_err(box.yaw, truth.yaw) < 1e-9


def test_a_role_heads_couple_order_is_a_vote_only_where_the_relations_carry_roles():
    cam = _camera()
    v = Box3D(-1.2, 4.6, 4.5, 1.8, 0.08)
    c = _contacts(v)
    contacts = {2: c["rr"], 3: c["fr"]}
    # the role head said "front" for both, and listed the couple rear first (its lower front probability first)
    rec = _record(cam, [(0, 2, "front"), (0, 3, "front")], [(2, 3)], n_vehicles=2, n_wheels=2)
    e = footprints_from_contacts(rec, cam, PRIOR, contacts)[0]
    assert e.evidence == "side" and e.role_vote == ROLE_COUPLE_LOGIT and _yaw_err(e.box.yaw, v.yaw) < 1e-6
    # without roles a couple's order is a rule's (left to right in the image): no vote
    rec = _record(cam, [(0, 2, None), (0, 3, None)], [(2, 3)], n_vehicles=2, n_wheels=2)
    assert footprints_from_contacts(rec, cam, PRIOR, contacts)[0].role_vote == 0.0


def test_aoe_over_tied_confidences_is_the_mean_of_all_tied_matches():
    # ground-truth boxes: every estimate of an evidence level has the same confidence; half of them point backwards
    frames = []
    for k in range(10):
        t = Box3D(5.0, 0.0, 4.5, 1.8, 0.0)
        e = replace(t, yaw=math.pi if k % 2 else 0.0)
        frames.append(([TrueVehicle(t)], [Scored(e, 0.9, 2)]))
    for order in (frames, frames[::-1]):
        scores = detection_scores(order, lambda t: True, lambda e: True)
        assert scores["aoe_deg"] == pytest.approx(90.0) and scores["aoe180_deg"] == pytest.approx(0.0, abs=1e-6)
    # distinct confidences still give nuScenes' running mean: the confident (right) half counts more
    ranked = [(tv, [replace(s[0], confidence=1.0 - 0.05 * k)]) for k, (tv, s) in enumerate(frames)]
    assert 0 < detection_scores(ranked, lambda t: True, lambda e: True)["aoe_deg"] < 90.0
    assert np.isfinite(detection_scores(ranked, lambda t: True, lambda e: True)["ate_m"])
