"""The logic-model baselines on Fig. 2-like cases, their fitting on train, and their JSON round trip."""

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from deepword.metrics import score_records
from deepword.priors import Mixture1D, Priors, make_pair_prior
from deepword.rules.baselines import (
    CoupleRule,
    Logic,
    LogicPlus,
    LogicPlusParams,
    Objects,
    PairFeatures,
    PairStats,
    PriorMethod,
    SearchGrids,
    assign_with_capacity,
    baseline_from_params,
    baseline_params,
    fit_couple_rule,
    fit_logic,
    fit_logic_plus,
    fit_prior,
    owner_objective,
    prepare_train,
)
from deepword.word_format import Record
from tests.deepword.tiny_word import make_record

GRIDS = SearchGrids.from_cfg(OmegaConf.load(Path(__file__).parents[3] / "conf/eval/default.yaml").baseline_grids)

NO_COUPLES = CoupleRule(centre=0.0, tolerance=-1.0)


def rec(boxes, relations=()):
    return Record(image="f.png", frame_id=0, camera="left", width=200, height=100,
                  boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7),
                  relations=[(v, w, None) for v, w in relations], wheel_pairs=[])


# Fig. 2: a tall far van (0) whose box reaches down over a near car (1); the near car's wheel (2) lies
# wholly inside both boxes, and the van's box is the smaller one, so the highest IoU is the wrong owner.
FIG2 = rec([[60, 0, 140, 83, 1, 0, 0], [0, 30, 150, 80, 1, 0, 1], [100, 58, 122, 80, 1, 1, 2],
            [66, 61, 86, 83, 1, 1, 3]], relations=[(1, 2), (0, 3)])


def owner_map(pred: Record) -> dict[int, int]:
    return pred.owner_of()


def test_logic_takes_highest_iou_vehicle_and_errs_on_fig2():
    pred = Logic(0.0, NO_COUPLES).predict(FIG2)
    assert owner_map(pred)[2] == 0  # the van: highest IoU, the paper's failure mode
    assert pred.boxes is not FIG2.boxes and np.array_equal(pred.boxes, FIG2.boxes)


def test_logic_threshold_leaves_lonely_wheel_without_owner():
    r = rec([[0, 0, 100, 50, 1, 0, 0], [150, 30, 170, 50, 1, 1, 1], [10, 30, 30, 50, 1, 1, 2]])
    assert owner_map(Logic(0.0, NO_COUPLES).predict(r)) == {2: 0}
    assert owner_map(Logic(0.5, NO_COUPLES).predict(r)) == {}


def bottom_only(**kw) -> LogicPlus:
    params = LogicPlusParams(min_containment=0.5, min_height=0.3, w_bottom=1.0, w_ratio=0, w_size=0, w_end=0,
                             w_contain=0, none_cost=2.0, **kw)
    return LogicPlus(params, PairStats(0, 1), PairStats(0, 1), NO_COUPLES)


def test_logic_plus_uses_bottom_alignment_on_fig2():
    assert owner_map(bottom_only().predict(FIG2)) == {2: 1, 3: 0}


def test_logic_plus_gates_wheels_in_the_upper_part():
    r = rec([[0, 0, 100, 50, 1, 0, 0], [10, 0, 30, 20, 1, 1, 1]])  # a "wheel" at the roof
    assert owner_map(bottom_only().predict(r)) == {}


def test_assignment_gives_at_most_four_wheels_per_vehicle():
    cost = np.zeros((6, 1))
    owner = assign_with_capacity(cost, none_cost=5.0)
    assert (owner == 0).sum() == 4 and (owner == -1).sum() == 2
    assert assign_with_capacity(np.zeros((0, 2)), 1.0).shape == (0,)


def test_couples_need_the_same_owner_and_are_ordered_by_x():
    r = make_record(np.random.default_rng(3), 0, 1)
    ids = r.box_ids[r.class_ids == 1]
    rule = CoupleRule(centre=1.0, tolerance=5.0)
    pred = Logic(0.0, rule).predict(r)
    assert pred.wheel_pairs == [tuple(sorted(ids, key=lambda b: r.xyxy[list(r.box_ids).index(b), 0]))]
    assert Logic(1.0, rule).predict(r).wheel_pairs == []  # no owners, no couples


def test_fitting_on_train_and_logic_plus_at_least_logic():
    rng = np.random.default_rng(0)
    train = [make_record(rng, i, int(rng.integers(1, 7))) for i in range(80)]
    test = [make_record(rng, 100 + i, int(rng.integers(3, 7))) for i in range(30)]
    for i, r in enumerate(test):
        r.image = f"t{i}.png"
    images = prepare_train(train, 0.0, 1000, seed=0)
    rule = fit_couple_rule(images, GRIDS.couple_tolerance)
    logic = fit_logic(images, rule, GRIDS.logic_iou)
    plus = fit_logic_plus(images, rule, GRIDS.logic_plus, rounds=1)
    plus_owners = [plus.owners_from(PairFeatures.of(im.obj)) for im in images]
    assert owner_objective(images, plus_owners) >= owner_objective(images, [logic.owners(im.obj) for im in images])
    scores = {m.name: score_records(test, {r.image: m.predict(r) for r in test}).percentages()
              for m in (logic, plus)}
    assert scores["logic_plus"]["wheel_acc"] >= scores["logic"]["wheel_acc"]
    assert scores["logic_plus"]["wheel_acc"] > 95 and scores["logic_plus"]["couple_f1"] > 90


def test_logic_plus_fits_the_same_rule_whatever_order_its_grid_lists_the_fields_in():
    # the cache key hashes the config with sorted keys: a reordered YAML must not fit another rule under the same key
    rng = np.random.default_rng(1)
    images = prepare_train([make_record(rng, i, int(rng.integers(1, 7))) for i in range(40)], 0.0, 1000, seed=0)
    rule = fit_couple_rule(images, GRIDS.couple_tolerance)
    orders = [dict(GRIDS.logic_plus), dict(reversed(GRIDS.logic_plus.items())), dict(sorted(GRIDS.logic_plus.items()))]
    fitted = [fit_logic_plus(images, rule, grid, rounds=1).params for grid in orders]
    assert fitted[1] == fitted[0] and fitted[2] == fitted[0]
    with pytest.raises(ValueError, match=r"logic_plus: \['w_tilt'\] are not LogicPlusParams fields"):
        fit_logic_plus(images, rule, {**GRIDS.logic_plus, "w_tilt": (0.0, 1.0)}, rounds=1)


def toy_priors() -> Priors:
    wv = make_pair_prior("prior", Mixture1D([1.0], [np.log(3.0)], [0.05]), None, 1, 0)
    ww = make_pair_prior("prior", Mixture1D([1.0], [np.log(4.0)], [0.05]), None, 1, 0)
    return Priors(wv, ww)


def test_prior_method_picks_highest_prior():
    # 200 x 100 image; vehicle 0 centre (100, 40); wheel (10x10) at distance giving ratio 3 -> prior 1
    size = 10 / 200 + 10 / 100
    dx = 3 * size / 2 * 200  # ratio = 2 * (dx / W) / size
    w = [100 + dx - 5, 35, 100 + dx + 5, 45]
    r = rec([[50, 20, 150, 60, 1, 0, 0], [0, 0, 20, 90, 1, 0, 1], w + [1, 1, 2]])
    method = PriorMethod(toy_priors(), 0.5, 0.5)
    assert method.scores(Objects.of(r))[0, 0] == pytest.approx(1.0)
    assert owner_map(method.predict(r)) == {2: 0}
    assert owner_map(PriorMethod(toy_priors(), 1.01, 0.5).predict(r)) == {}
    rng = np.random.default_rng(1)
    fitted = fit_prior(prepare_train([make_record(rng, i, 3) for i in range(10)], 0.0, 100, 0), toy_priors(),
                       GRIDS.prior_owner, GRIDS.prior_couple)
    assert 0.0 <= fitted.threshold <= 1.0


@pytest.mark.parametrize("method", [Logic(0.05, CoupleRule(1.0, 0.3)),
                                    LogicPlus(LogicPlusParams(w_end=2.0), PairStats(0.4, 0.1), PairStats(-0.8, 0.2),
                                              CoupleRule(1.0, 0.3)),
                                    PriorMethod(toy_priors(), 0.2, 0.3)])
def test_params_round_trip(method):
    back = baseline_from_params(method.name, baseline_params(method), priors=toy_priors())
    r = make_record(np.random.default_rng(5), 0, 5)
    assert back.predict(r).relations == method.predict(r).relations
    assert baseline_params(back) == baseline_params(method)


def test_unknown_baseline_is_an_error():
    with pytest.raises(ValueError, match="unknown baseline"):
        baseline_from_params("magic", {})
    with pytest.raises(ValueError, match="needs the priors"):
        baseline_from_params("prior", {"threshold": 0.1, "couple_threshold": 0.1})
