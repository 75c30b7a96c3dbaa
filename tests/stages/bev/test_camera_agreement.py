"""The facing network checked without labels: how often two cameras' votes on one vehicle agree, the accuracy that
implies, and the line ``deepword infer`` prints from it."""

import math

import pytest

from deepword.footprint import (
    MIN_CAMERA_PAIRS,
    Estimate,
    camera_agreement,
    facing_logit,
    facing_trust,
    fuse_frame,
    implied_accuracy,
    weigh_facing,
)
from deepword.format_3d import Box3D
from deepword.inference.footprints import Frame, facing_check
from stages.bev.stage import render_facing


def _vehicle(votes: dict[str, float], turned: set[str] = frozenset()) -> tuple[Box3D, list[Estimate]]:
    """A fused vehicle facing +x, one estimate per camera voting ``votes[camera]`` for its own yaw: +x, or -x for the
    cameras in ``turned`` (so the same vote means the other way)."""
    box = Box3D(5.0, 0.0, 4.5, 1.8, 0.0)
    group = [Estimate(Box3D(5.0, 0.0, 4.5, 1.8, math.pi if cam in turned else 0.0), "side", cam, 0, f"{cam}.png",
                      facing_vote=vote) for cam, vote in votes.items()]
    return box, group


def test_camera_pairs_agree_when_their_votes_point_the_vehicle_the_same_way():
    fused = [
        _vehicle({"front": 2.0, "left": 1.0}),                            # agree
        _vehicle({"front": 2.0, "left": 1.0}, turned={"left"}),          # left's yaw is turned: it votes the other way
        _vehicle({"front": 2.0, "left": -1.0}, turned={"left"}),         # turned twice: agree
        _vehicle({"front": 1.0, "left": 1.0, "rear": -1.0}),             # 3 pairs, 1 agrees
        _vehicle({"front": 3.0}),                                        # one camera: no pair
        _vehicle({"front": 3.0, "left": 0.0}),                           # left did not vote: no pair
    ]
    assert camera_agreement(fused) == (6, 3)


def test_two_estimates_of_one_camera_count_as_one_vote():
    box, group = _vehicle({"front": 2.0, "left": 1.0})
    group.append(Estimate(Box3D(5.2, 0.0, 4.5, 1.8, 0.0), "wheel", "front", 1, "front.png", facing_vote=-0.5))
    assert camera_agreement([(box, group)]) == (1, 1)   # front sums to +1.5


@pytest.mark.parametrize("p", [0.5, 0.69, 0.92, 1.0])
def test_implied_accuracy_inverts_the_agreement_of_independent_votes(p):
    agree = p * p + (1 - p) * (1 - p)
    assert implied_accuracy(10_000, round(agree * 10_000)) == pytest.approx(p, abs=2e-3)


def test_implied_accuracy_is_a_coin_at_chance_and_none_without_pairs():
    assert implied_accuracy(10, 3) == 0.5 and implied_accuracy(0, 0) is None


def _frames(agreeing: int, disagreeing: int) -> dict[int, Frame]:
    fused = ([_vehicle({"front": 1.0, "left": 1.0})] * agreeing + [_vehicle({"front": 1.0, "left": -1.0})] * disagreeing)
    return {0: Frame(0, [], fused, {})}


def test_infer_says_whether_the_facing_network_holds_on_the_frames():
    assert facing_check({0: Frame(0, [], [_vehicle({"front": 1.0})], {})}, 0.92) is None   # no vehicle two cameras saw
    holds = facing_check(_frames(36, 4), 0.92)   # 90 % agree: ~95 %
    assert holds.startswith("facing network: two cameras' votes on one vehicle agree for 36 of 40 camera pairs")
    assert "~95 %" in holds and "92.0 % on its val split" in holds and "well below" not in holds
    fails = facing_check(_frames(25, 15), 0.92)  # 62.5 %: ~75 %
    assert "~75 %" in fails and "well below, so its votes counted x 0.45" in fails and "pipeline.skip=[facing]" in fails
    few = facing_check(_frames(2, 3), 0.92)
    assert f"too few pairs to judge (under {MIN_CAMERA_PAIRS})" in few and "well below" not in few


def test_the_bev_report_sets_the_label_free_figure_beside_the_truths():
    line, = render_facing({"gt": {"acc": 86.6, "vehicles": 1053.0, "camera_pairs": 109.0, "camera_agreement": 85.3,
                                  "implied_acc": 92.0}})
    assert line == ("- gt boxes: the facing vectors point within 90 deg of the true facing for 86.6 % of the 1053 "
                    "matched vehicles with 3D truth; without labels, two cameras' votes agree on 85.3 % of 109 camera "
                    "pairs, as a network right for 92.0 % would")
    assert render_facing({"gt": {"acc": 50.0, "vehicles": 2.0, "camera_pairs": 0.0}})[0].endswith("with 3D truth")


def test_votes_keep_their_weight_unless_the_cameras_say_the_network_is_well_below_its_val_accuracy():
    def fused(agreeing, disagreeing):
        return _frames(agreeing, disagreeing)[0].fused

    assert facing_trust(fused(36, 4), 0.92) == 1.0    # implied ~95 %
    assert facing_trust(fused(33, 7), 0.92) == 1.0    # implied ~88 %: within FACING_DOUBT_POINTS
    assert facing_trust(fused(3, 2), 0.92) == 1.0     # too few pairs to act on
    low = facing_trust(fused(25, 15), 0.92)           # implied 75 %: the weight of a 75 % vote against a 92 % one
    assert low == pytest.approx(facing_logit(0.75) / facing_logit(0.92)) and 0.4 < low < 0.5
    assert facing_trust(fused(10, 30), 0.92) == 0.0   # at chance or below: no weight


def test_weighed_votes_can_lose_to_the_roles():
    box, group = _vehicle({"front": 1.0})
    back = [group[0], Estimate(Box3D(5.1, 0.0, 4.5, 1.8, 0.0), "wheel", "left", 0, "left.png", role_vote=-0.8)]
    assert weigh_facing(back, 1.0) is back
    ((kept, _),) = fuse_frame(back, 1.5)
    ((turned, _),) = fuse_frame(weigh_facing(back, 0.5), 1.5)
    assert abs(kept.yaw) < 1e-6 and abs(abs(turned.yaw) - math.pi) < 1e-6
