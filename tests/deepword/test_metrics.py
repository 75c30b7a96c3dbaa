"""§7 metrics on hand-made cases."""

import numpy as np
import pytest

from deepword.metrics import Counts, match_boxes, score_image, score_records
from deepword.word_format import Record


def rec(boxes, relations=(), pairs=(), image="a.png"):
    b = np.array([list(map(float, x)) for x in boxes], dtype=np.float64).reshape(-1, 7)
    return Record(image=image, frame_id=0, camera="front", width=200, height=100, boxes=b,
                  relations=[tuple(r) if len(r) == 3 else (r[0], r[1], None) for r in relations],
                  wheel_pairs=[tuple(p) for p in pairs])


# vehicle 0 with wheels 1, 2 (a couple); wheel 3 belongs to no vehicle
GT = rec([[0, 0, 100, 50, 1, 0, 0], [5, 30, 25, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2],
          [150, 30, 170, 50, 1, 1, 3]], relations=[(0, 1), (0, 2)], pairs=[(1, 2)])


def with_relations(relations, pairs=()):
    return rec(GT.boxes.tolist(), relations, pairs)


def test_perfect_prediction():
    m = score_image(GT, with_relations([(0, 1), (0, 2)], [(2, 1)])).percentages()  # couple order ignored
    assert m == {"wheel_acc": 100.0, "pair_precision": 100.0, "pair_recall": 100.0, "pair_f1": 100.0,
                 "couple_f1": 100.0, "image_acc": 100.0}


def test_wheel_without_owner_must_be_predicted_without_owner():
    c = score_image(GT, with_relations([(0, 1), (0, 2), (0, 3)]))
    assert (c.wheels, c.wheels_correct, c.images_correct) == (3, 2, 0)
    assert (c.pair_tp, c.pair_fp, c.pair_fn) == (2, 1, 0)
    assert c.percentages()["pair_precision"] == pytest.approx(200 / 3)


def test_missed_relation_and_no_couples():
    c = score_image(GT, with_relations([(0, 1)]))
    assert (c.wheels_correct, c.pair_tp, c.pair_fn, c.couple_fn) == (2, 1, 1, 1)
    m = c.percentages()
    assert m["wheel_acc"] == pytest.approx(200 / 3) and m["pair_recall"] == 50.0 and m["couple_f1"] == 0.0


def test_duplicate_prediction_is_a_false_positive():
    c = score_image(GT, with_relations([(0, 1), (0, 1), (0, 2)]))
    assert (c.pair_tp, c.pair_fp, c.wheels_correct) == (2, 1, 3)


def test_prediction_to_a_missing_box_is_wrong():
    c = score_image(GT, with_relations([(0, 1), (99, 2)]))  # vehicle 99 does not exist
    assert (c.pair_tp, c.pair_fp, c.wheels_correct, c.images_correct) == (1, 1, 2, 0)


def test_wheel_with_two_owners_is_wrong():
    two = rec(GT.boxes.tolist() + [[0, 0, 60, 50, 1, 0, 7]], [(0, 1), (7, 1), (0, 2)])
    c = score_image(rec(GT.boxes.tolist() + [[120, 0, 199, 50, 1, 0, 7]], [(0, 1), (0, 2)]), two)
    assert c.wheels_correct == 2  # wheel 1 given to 0 and 7: wrong; wheels 2, 3 right


def test_image_without_vehicles_or_wheels_is_defined():
    empty = rec([])
    c = score_image(empty, empty)
    assert (c.images, c.images_correct, c.wheels) == (1, 1, 0)
    assert c.percentages() == {"wheel_acc": 100.0, "pair_precision": 100.0, "pair_recall": 100.0,
                               "pair_f1": 100.0, "couple_f1": 100.0, "image_acc": 100.0}
    wheels_only = rec([[5, 30, 25, 50, 1, 1, 1]])
    assert score_image(wheels_only, wheels_only).percentages()["wheel_acc"] == 100.0
    m = Counts().percentages()
    assert not any(np.isnan(v) for v in m.values())


def test_small_wheels_are_not_evaluated_and_predictions_on_them_ignored():
    small = rec([[0, 0, 100, 50, 1, 0, 0], [5, 45, 9, 50, 1, 1, 1], [75, 30, 95, 50, 1, 1, 2]],
                relations=[(0, 1), (0, 2)])
    pred = rec(small.boxes.tolist(), [(0, 2)])
    c = score_image(small, pred, min_box_px=8)
    assert (c.wheels, c.wheels_correct, c.pair_fn, c.pair_fp) == (1, 1, 0, 0)


def test_matching_detected_boxes_greedy_by_score():
    det = rec([[2, 1, 101, 52, 0.9, 0, 10],      # vehicle 0
               [6, 31, 25, 50, 0.8, 1, 11],      # wheel 1
               [5, 30, 24, 49, 0.3, 1, 12],      # duplicate of wheel 1, lower score: unmatched
               [76, 30, 96, 51, 0.7, 1, 13],     # wheel 2
               [140, 0, 160, 10, 0.9, 1, 14]])   # nothing there
    assert match_boxes(GT, det) == {10: 0, 11: 1, 13: 2}
    assert match_boxes(GT, GT) == {0: 0, 1: 1, 2: 2, 3: 3}  # identity on ground-truth boxes
    pred = rec(det.boxes.tolist(), [(10, 11), (10, 12), (10, 13)], [(11, 13)])
    c = score_image(GT, pred)
    # wheel 3 was not detected: wrong although it has no owner; the duplicate's relation is a false positive
    assert (c.wheels_correct, c.pair_tp, c.pair_fp, c.couple_tp) == (2, 2, 1, 1)


def test_detected_class_must_agree():
    det = rec([[0, 0, 100, 50, 0.9, 1, 10]])  # a "wheel" on the vehicle box: no match across classes
    assert match_boxes(GT, det) == {}


def test_unmatched_owner_is_wrong():
    det = rec([[150, 0, 199, 60, 0.9, 0, 10], [5, 30, 25, 50, 0.8, 1, 11]])
    c = score_image(GT, rec(det.boxes.tolist(), [(10, 11)]))
    assert c.wheels_correct == 0 and c.pair_fp == 1


def test_score_records_sums_and_missing_images_have_no_relations():
    other = rec(GT.boxes.tolist(), GT.relations, GT.wheel_pairs, image="b.png")
    total = score_records([GT, other], {"a.png": with_relations([(0, 1), (0, 2)], [(1, 2)])})
    assert (total.images, total.images_correct, total.wheels, total.wheels_correct) == (2, 1, 6, 4)


def random_image(rng: np.random.Generator, image: str) -> tuple[Record, Record]:
    """Ground truth and a one-owner prediction on its boxes: vehicles, wheels of 4-20 px (some under the
    8 px evaluation floor), random owners and couples on both sides."""
    n_v, n_w = int(rng.integers(0, 4)), int(rng.integers(0, 7))
    boxes = [[x, 10, x + 60, 60, 1, 0, i] for i, x in enumerate(rng.uniform(0, 130, n_v))]
    for k in range(n_w):
        size = float(rng.uniform(4, 20))
        x = float(rng.uniform(0, 180))
        boxes.append([x, 40, x + size, 40 + size, 1, 1, n_v + k])
    wheels = list(range(n_v, n_v + n_w))

    def draw() -> tuple[list, list]:
        relations = [(int(rng.integers(n_v)), w, None) for w in wheels if n_v and rng.random() < 0.7]
        order = list(rng.permutation(wheels)) if wheels else []
        couples = [(int(order[i]), int(order[i + 1])) for i in range(0, len(order) - 1, 2) if rng.random() < 0.5]
        return relations, couples

    gt_rel, gt_pairs = draw()
    pred_rel, pred_pairs = draw()
    return rec(boxes, gt_rel, gt_pairs, image), rec(boxes, pred_rel, pred_pairs, image)


def test_validation_baseline_fitting_and_evaluation_count_alike():
    """The three users of the §7 metrics give the same counts for the same decisions: evaluation on records,
    the baselines on owner indices, relation validation on decoded matrices over the evaluated wheels."""
    import torch

    from deepword.metrics import evaluated_mask
    from deepword.relation_graph import relation_targets
    from deepword.rules.baselines import prepare_train, train_counts
    from stages.relation.decode import relation_counts

    rng = np.random.default_rng(7)
    for i in range(200):
        gt, pred = random_image(rng, f"{i}.png")
        by_record = score_image(gt, pred, min_box_px=8)

        (train,) = prepare_train([gt], min_box_px=8, max_images=1, seed=0)
        v_index = {int(gt.box_ids[k]): j for j, k in enumerate(train.obj.vehicles)}
        owner_of = {w: v for v, w, _ in pred.relations}
        owners = np.array([v_index.get(owner_of.get(int(gt.box_ids[k]), -1), -1) for k in train.obj.wheels])
        w_index = {int(gt.box_ids[k]): j for j, k in enumerate(train.obj.wheels)}
        by_indices = train_counts(train, owners, [(w_index[a], w_index[b]) for a, b in pred.wheel_pairs])

        owner_t, couple_t, _ = relation_targets(gt)
        n = len(gt.boxes)
        pred_owner = np.zeros((n, n), dtype=bool)
        pred_couple = np.zeros((n, n), dtype=bool)
        for v, w, _ in pred.relations:
            pred_owner[w, v] = True  # box ids are row indices here
        for a, b in pred.wheel_pairs:
            pred_couple[a, b] = pred_couple[b, a] = True
        by_matrices = relation_counts(*(torch.from_numpy(a)[None] for a in (
            pred_owner, owner_t, pred_couple, couple_t, gt.class_ids.astype(np.int64),
            evaluated_mask(gt.xyxy, gt.class_ids, 8))))
        assert Counts(**{k: int(v) for k, v in by_matrices.items()}) == by_record == by_indices, gt.image


def test_no_couples_anywhere_is_a_perfect_couple_f1_for_every_user():
    from deepword.rules.baselines import couple_f1, prepare_train

    gt = rec(GT.boxes.tolist(), [(0, 1), (0, 2)])
    assert score_image(gt, with_relations([(0, 1), (0, 2)])).percentages()["couple_f1"] == 100.0
    assert couple_f1(prepare_train([gt], 0.0, 1, 0), [[]]) == 100.0


def test_a_prediction_in_an_ignore_region_counts_neither_way():
    # ground truth: vehicle 0 with wheels 1, 2; a second vehicle too hidden to label, with a visible wheel: ignore
    # regions (vehicle 120-180, wheel 150-160)
    gt = rec(GT.boxes[:3].tolist(), relations=[(0, 1), (0, 2)], pairs=[(1, 2)])
    gt.ignore = np.array([[120, 10, 180, 50, 0], [150, 40, 160, 50, 1]], dtype=np.float64)
    found = [[0, 0, 100, 50, 0.9, 0, 10], [5, 30, 25, 50, 0.9, 1, 11], [75, 30, 95, 50, 0.9, 1, 12]]
    hidden = [[121, 10, 180, 50, 0.6, 0, 13], [150, 41, 160, 50, 0.5, 1, 14]]
    claims = [(10, 11), (10, 12), (13, 14)]
    c = score_image(gt, rec(found + hidden, claims, [(11, 12), (14, 11)]))
    assert (c.pair_tp, c.pair_fp, c.pair_fn) == (2, 0, 0) and (c.couple_tp, c.couple_fp) == (1, 0)
    assert c.images_correct == 1
    # a real wheel claimed by the hidden vehicle's box as well: neither right nor wrong either, the wheel keeps its
    # one owner
    both = score_image(gt, rec(found + hidden, claims + [(13, 12)]))
    assert both.pair_fp == 0 and both.wheels_correct == 2
    # without the regions both are false; a box of the other class, or mostly outside, is not absorbed
    bare = rec(GT.boxes[:3].tolist(), relations=[(0, 1), (0, 2)], pairs=[(1, 2)])
    assert score_image(bare, rec(found + hidden, claims)).pair_fp == 1
    in_a_vehicle_region = [[125, 15, 135, 25, 0.5, 1, 15]]  # a wheel box inside the hidden vehicle's region only
    assert score_image(gt, rec(found + hidden + in_a_vehicle_region, claims + [(10, 15)])).pair_fp == 1
    half_out = [[155, 41, 175, 50, 0.5, 1, 14]]  # a quarter of it inside the hidden wheel's region
    assert score_image(gt, rec(found + half_out, [(10, 11), (10, 12), (10, 14)])).pair_fp == 1
