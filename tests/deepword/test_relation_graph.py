"""Graph inputs: crops, coordinate planes, prior adjacency, candidate pairs, targets, padding, caching."""

import numpy as np
import pytest
import torch

from deepword.relation_graph import (
    InputConfig,
    SplitInputs,
    adjacency,
    candidate_pairs,
    check_object_counts,
    crop_object,
    node_tensor,
    node_validity,
    pair_priors,
    relation_targets,
)
from deepword.word_format import Record
from tests.stages.relation import relation_data as rd


def test_crop_keeps_box_place_and_blacks_out_outside_image():
    rgb = np.full((100, 100, 3), 200, dtype=np.uint8)
    rgb[:, 50:] = 50
    # box at the left border: margin 0.5 reaches outside the image on the left
    crop = crop_object(rgb, [0, 20, 40, 60], size=32, margin=0.5)
    assert crop.shape == (32, 32, 3) and crop.dtype == np.uint8
    assert (crop[:, :6] == 0).all()                # grown box left of x=0: black
    assert (crop[10:20, 12:20] == 200).all()       # inside the box: the image
    assert (crop[10:20, -4:] == 50).all()          # right margin reaches the darker half (x >= 50)


def test_min_crop_px_grows_small_boxes_about_their_centre_and_leaves_large_ones():
    rgb = np.zeros((100, 100, 3), dtype=np.uint8)
    rgb[40:60, 40:60] = 100   # context around the small box
    rgb[48:52, 48:52] = 255   # the 4 x 4 box
    small = [48, 48, 52, 52]
    assert (crop_object(rgb, small, size=20, margin=0.0) == 255).all()     # the box alone
    grown = crop_object(rgb, small, size=20, margin=0.0, min_px=20)       # 20 x 20 about (50, 50)
    assert (grown[8:12, 8:12] == 255).all() and (grown[:6] == 100).all() and (grown[:, -6:] == 100).all()
    large = [10, 20, 90, 80]
    assert np.array_equal(crop_object(rgb, large, 32, 0.2, min_px=20), crop_object(rgb, large, 32, 0.2))
    with pytest.raises(ValueError, match="min_crop_px"):
        InputConfig(min_crop_px=-1)


def test_node_tensor_is_rgb_in_unit_range_plus_four_constant_planes():
    crops = torch.full((2, 3, 8, 8), 255, dtype=torch.uint8)
    coords = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.5, 0.6, 0.7, 0.8]])
    x = node_tensor(crops, coords)
    assert x.shape == (2, 7, 8, 8) and x.dtype == torch.float32
    assert torch.all(x[:, :3] == 1.0)
    assert torch.allclose(x[1, 3:, 4, 4], coords[1]) and torch.all(x[0, 5] == 0.3)


def test_node_tensor_in_channels_last_holds_the_same_values_laid_out_nhwc():
    g = torch.Generator().manual_seed(2)
    crops = torch.randint(0, 256, (5, 3, 12, 10), generator=g, dtype=torch.uint8)
    coords = torch.rand(5, 4, generator=g)
    nhwc = node_tensor(crops, coords, channels_last=True)
    assert nhwc.is_contiguous(memory_format=torch.channels_last) and not nhwc.is_contiguous()
    assert torch.equal(nhwc, node_tensor(crops, coords))


def _scene():
    # vehicle 0, vehicle 1, wheel 2, wheel 3 (wheel 3 tiny)
    xyxy = np.array([[10, 10, 110, 60], [100, 20, 200, 70], [20, 45, 35, 60], [90, 50, 95, 55]], dtype=float)
    classes = np.array([0, 0, 1, 1], dtype=np.int8)
    return xyxy, classes


def test_adjacency_has_priors_on_candidates_self_loops_and_no_vehicle_vehicle_edges():
    xyxy, classes = _scene()
    priors = pair_priors(xyxy, classes, 320, 240, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL)
    assert np.allclose(priors, priors.T) and priors[0, 1] == 0 and (priors >= 0).all() and (priors <= 1).all()
    assert priors[0, 2] > 0 and priors[2, 3] > 0
    valid = np.ones(4, dtype=bool)
    cand = candidate_pairs(classes, valid, priors, 0.0)
    adj = adjacency(priors, cand, valid, "prior")
    assert np.allclose(np.diag(adj), 1) and adj[0, 1] == adj[1, 0] == 0
    assert adj[2, 0] == pytest.approx(priors[2, 0])
    assert np.array_equal(adjacency(priors, cand, valid, "uniform") > 0, adj > 0)
    assert set(np.unique(adjacency(priors, cand, valid, "uniform"))) == {0.0, 1.0}


def test_small_mask_removes_a_node_from_the_graph():
    xyxy, classes = _scene()
    valid = node_validity(xyxy, small_mask_px=8)
    assert valid.tolist() == [True, True, True, False]
    priors = pair_priors(xyxy, classes, 320, 240, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL)
    cand = candidate_pairs(classes, valid, priors, 0.0)
    adj = adjacency(priors, cand, valid, "prior")
    assert not cand[3].any() and not cand[:, 3].any() and not adj[3].any() and not adj[:, 3].any()


def test_min_prior_keeps_only_likely_candidates():
    xyxy, classes = _scene()
    priors = pair_priors(xyxy, classes, 320, 240, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL)
    eps = float(np.median(priors[priors > 0]))
    cand = candidate_pairs(classes, np.ones(4, dtype=bool), priors, eps)
    assert cand.any() and (priors[cand] >= eps).all()
    assert cand.sum() < candidate_pairs(classes, np.ones(4, dtype=bool), priors, 0.0).sum()


def test_targets_are_symmetric_and_roles_come_from_relations_or_couple_order():
    boxes = np.array([[0, 0, 50, 30, 1, 0, 7], [5, 20, 15, 30, 1, 1, 3], [35, 20, 45, 30, 1, 1, 4],
                      [60, 20, 70, 30, 1, 1, 9]], dtype=float)
    rec = Record(image="a.png", frame_id=0, camera="left", width=100, height=50, boxes=boxes,
                 relations=[(7, 3, None), (7, 4, "front")], wheel_pairs=[(3, 4)])
    owner, couple, role = relation_targets(rec)
    assert owner[0, 1] == owner[1, 0] == owner[0, 2] == 1 and owner.sum() == 4
    assert couple[1, 2] == couple[2, 1] == 1 and couple.sum() == 2
    assert role.tolist() == [-1, 0, 1, -1]  # wheel 3 is rear by the couple order; wheel 9 has no role


def test_split_is_padded_and_round_trips_through_npz(tmp_path):
    cfg = InputConfig(input_size=16, max_objects=16)
    recs = rd.records(3)
    split = rd.split(recs, cfg)
    n_objects = [len(r.boxes) for r in recs]
    assert split.crops.shape == (sum(n_objects), 3, 16, 16) and split.offsets.tolist()[-1] == sum(n_objects)
    assert split.adj.shape == (3, 16, 16) and split.valid.sum(1).tolist() == n_objects
    k = n_objects[0]
    assert (split.classes[0, k:] == -1).all() and not split.adj[0, k:].any() and not split.adj[0, :, k:].any()
    split.save(tmp_path / "train.npz")
    again = SplitInputs.load(tmp_path / "train.npz")
    for key in SplitInputs.__dataclass_fields__:
        assert np.array_equal(getattr(again, key), getattr(split, key)), key


def test_a_split_built_several_images_at_a_time_is_the_split_built_one_at_a_time():
    from deepword.relation_graph import build_split

    cfg = InputConfig(input_size=16, max_objects=16)
    recs = rd.records(7, seed=3)
    alone = rd.split(recs, cfg)
    threaded = build_split(recs, rd.render, cfg, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL, threads=3)
    for key in SplitInputs.__dataclass_fields__:
        assert np.array_equal(getattr(threaded, key), getattr(alone, key)), key


def test_too_many_objects_fail_naming_the_image():
    recs = rd.records(2)
    with pytest.raises(ValueError, match=r"images/left/00000\.png.*max_objects=2"):
        check_object_counts(recs, 2)


def test_mirrored_graph_is_the_graph_of_the_mirrored_image():
    """``mirrored`` (what hflip trains on and flip averaging scores) equals building the graph of the mirrored
    image and boxes: same priors, candidates and adjacency, mirrored coordinates, flipped crops."""
    from deepword.relation_graph import build_graph, mirrored
    from stages.detector.augment import flip_image, flip_record

    cfg = InputConfig(input_size=16, max_objects=32)
    rec = rd.records(1, seed=3)[0]
    rgb = rd.render(rec)
    built = build_graph(flip_record(rec), flip_image(rgb), cfg, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL)
    mirror = mirrored(build_graph(rec, rgb, cfg, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL))
    for name in ("classes", "valid", "cand"):
        assert np.array_equal(getattr(mirror, name), getattr(built, name)), name
    assert np.allclose(mirror.adj, built.adj) and np.allclose(mirror.coords, built.coords, atol=1e-6)
    # crops resampled from the mirrored image could differ from flipped crops by sub-pixel rounding (here they
    # do not; an unflipped crop differs from them by ~30 grey levels on average)
    assert np.abs(mirror.crops.astype(int) - built.crops.astype(int)).mean() < 1
    assert np.array_equal(mirrored(mirror).crops, build_graph(rec, rgb, cfg, rd.WHEEL_VEHICLE, rd.WHEEL_WHEEL).crops)
