"""RelationNet: shapes per backbone, padding invariance, permutation equivariance, attention, decoding."""

import numpy as np
import pytest
import torch

from deepword.relation_graph import InputConfig, node_tensor
from stages.relation.backbone_spec import CONV_FC, RESNET18
from stages.relation.decode import (
    decode_couples,
    decode_owners,
    metrics_from_counts,
    relation_counts,
    role_counts,
    role_percentages,
)
from stages.relation.model import EDGE_FEATURES, ModelConfig, RelationNet, count_parameters, pair_geometry
from tests.stages.relation import relation_data as rd

torch.set_num_threads(1)


def conv_fc(input_size: int, expansion: int = 1) -> dict:
    return {"_target_": CONV_FC, "input_size": input_size, "expansion": expansion}


def _net(**kw) -> RelationNet:
    torch.manual_seed(0)
    cfg = dict(backbone=conv_fc(16), hidden=32, embed_dim=16, gat_hidden=16)
    cfg.update(kw)
    return RelationNet(ModelConfig(**cfg)).eval()


def _inputs(max_objects: int, size: int = 16, n_images: int = 2):
    split = rd.split(rd.records(n_images, seed=1, max_cars=3), InputConfig(input_size=size, max_objects=max_objects))
    crops = torch.zeros((n_images, max_objects, 3, size, size), dtype=torch.uint8)
    for i in range(n_images):
        a, b = split.offsets[i], split.offsets[i + 1]
        crops[i, : b - a] = torch.from_numpy(split.crops[a:b])
    x = node_tensor(crops, torch.from_numpy(split.coords))
    return x, torch.from_numpy(split.adj), torch.from_numpy(split.cand).float(), split


@pytest.mark.parametrize("backbone,size", [(conv_fc(28), 28), (conv_fc(56), 56), (conv_fc(56, 4), 56),
                                           ({"_target_": RESNET18, "input_size": 56, "base_width": 8}, 56)])
def test_output_shapes_per_backbone(backbone, size):
    net = _net(backbone=backbone)
    x, adj, cand, _ = _inputs(12, size=size)
    owner, couple, front = net(x, adj, cand)
    assert owner.shape == couple.shape == (2, 12, 12) and front.shape == (2, 12)
    assert torch.all(owner.abs() <= 1 + 1e-5) and torch.all((front >= 0) & (front <= 1))
    assert torch.all(owner[cand == 0] == 0)


def test_resnet18_at_full_width_is_resnet18_sized():
    net = RelationNet(ModelConfig(backbone={"_target_": RESNET18, "input_size": 56}))
    assert 11.0e6 < count_parameters(net.backbone) < 11.5e6  # torchvision's resnet18 has 11.7M with its 1000-way fc


GEOMETRY_OPTIONS = [{}, {"edge_geometry": True}, {"edge_geometry": True, "geometry_gate": True}]


@pytest.mark.parametrize("geometry", GEOMETRY_OPTIONS)
def test_padding_never_changes_real_outputs(geometry):
    net = _net(**geometry)
    x, adj, cand, split = _inputs(12)
    n_big = 20
    pad = n_big - 12
    x_big = torch.nn.functional.pad(x, (0, 0, 0, 0, 0, 0, 0, pad))
    adj_big = torch.nn.functional.pad(adj, (0, pad, 0, pad))
    cand_big = torch.nn.functional.pad(cand, (0, pad, 0, pad))
    with torch.no_grad():
        small, big = net(x, adj, cand), net(x_big, adj_big, cand_big)
    for i, k in enumerate(split.valid.sum(1)):
        assert torch.allclose(small[0][i, :k, :k], big[0][i, :k, :k], atol=1e-6)
        assert torch.allclose(small[1][i, :k, :k], big[1][i, :k, :k], atol=1e-6)
        assert torch.allclose(small[2][i, :k], big[2][i, :k], atol=1e-6)


@pytest.mark.parametrize("geometry", GEOMETRY_OPTIONS)
def test_permuting_objects_permutes_outputs(geometry):
    net = _net(**geometry)
    x, adj, cand, split = _inputs(12, n_images=1)
    k = int(split.valid[0].sum())
    perm = torch.cat([torch.randperm(k, generator=torch.Generator().manual_seed(3)), torch.arange(k, 12)])
    with torch.no_grad():
        out = net(x, adj, cand)
        out_p = net(x[:, perm], adj[:, perm][:, :, perm], cand[:, perm][:, :, perm])
    assert torch.allclose(out_p[0], out[0][:, perm][:, :, perm], atol=1e-5)
    assert torch.allclose(out_p[1], out[1][:, perm][:, :, perm], atol=1e-5)
    assert torch.allclose(out_p[2], out[2][:, perm], atol=1e-6)


def test_attention_sums_to_one_over_each_nodes_neighbours():
    net = _net()
    x, adj, cand, split = _inputs(12)
    with torch.no_grad():
        _, scale = net.edge_weights(net.embed(x), adj)
    neighbours = adj > 0
    valid = torch.from_numpy(split.valid)
    assert torch.allclose(scale.sum(-1)[valid], torch.ones(int(valid.sum())), atol=1e-6)
    assert torch.all(scale[~neighbours] == 0)          # nothing leaks to non-neighbours or padding
    assert torch.all(scale.sum(-1)[~valid] == 0)        # padded rows are empty
    assert scale[neighbours].std() > 0                 # re-weighting, not a constant


def test_without_gat_the_edge_weights_are_the_row_normalised_priors():
    net = _net(gat=False)
    x, adj, _, _ = _inputs(12)
    with torch.no_grad():
        weights, scale = net.edge_weights(net.embed(x), adj)
    expected = adj / adj.sum(-1, keepdim=True).clamp_min(1e-12)
    assert torch.allclose(weights, expected) and torch.equal(scale, (adj > 0).float())


def test_one_owner_decode_keeps_each_wheels_best_vehicle_above_threshold():
    classes = torch.tensor([[0, 0, 1, 1]])
    cand = torch.ones(1, 4, 4)
    scores = torch.zeros(1, 4, 4)
    scores[0, 2, 0], scores[0, 2, 1] = 0.9, 0.7   # wheel 2: both vehicles above 0.5
    scores[0, 3, 0], scores[0, 3, 1] = 0.4, 0.3   # wheel 3: none above 0.5
    plain = decode_owners(scores, classes, cand, 0.5, one_owner=False)
    one = decode_owners(scores, classes, cand, 0.5, one_owner=True)
    assert plain[0, 2].tolist() == [True, True, False, False] and not plain[0, 3].any()
    assert one[0, 2].tolist() == [True, False, False, False] and not one[0, 3].any()
    cand[0, 2, 0] = 0                              # a non-candidate pair is never predicted
    assert decode_owners(scores, classes, cand, 0.5, True)[0, 2].tolist() == [False, True, False, False]


def test_min_containment_gives_a_wheel_sticking_out_of_its_best_vehicle_to_the_next_or_to_none():
    classes = torch.tensor([[0, 0, 1, 1]])
    # vehicle 0 (big), vehicle 1 (inside-left of 0), wheel 2 inside both, wheel 3 half below vehicle 0's box
    coords = torch.tensor([[[0.0, 0.0, 0.8, 0.5], [0.0, 0.1, 0.3, 0.45], [0.1, 0.3, 0.2, 0.4], [0.5, 0.45, 0.6, 0.55]]])
    cand = torch.ones(1, 4, 4)
    scores = torch.zeros(1, 4, 4)
    scores[0, 2, 0], scores[0, 2, 1] = 0.9, 0.7   # wheel 2 prefers vehicle 0; both boxes hold it
    scores[0, 3, 0] = 0.9                          # wheel 3 prefers vehicle 0, which holds only half of it
    paper = decode_owners(scores, classes, cand, 0.5, True)
    assert paper[0, 2].tolist() == [True, False, False, False] and paper[0, 3].tolist() == [True, False, False, False]
    ruled = decode_owners(scores, classes, cand, 0.5, True, coords, 0.8)
    assert ruled[0, 2].tolist() == [True, False, False, False]   # unchanged: it lies inside its best vehicle
    assert not ruled[0, 3].any()                                   # half inside < 0.8: no owner
    assert decode_owners(scores, classes, cand, 0.5, True, coords, 0.5)[0, 3].tolist() == [True, False, False, False]
    scores[0, 2, 0] = 0.0                                          # then it takes the next vehicle holding it
    assert decode_owners(scores, classes, cand, 0.5, True, coords, 0.8)[0, 2].tolist() == [False, True, False, False]
    with pytest.raises(ValueError, match="coords"):
        decode_owners(scores, classes, cand, 0.5, True, None, 0.8)


def test_couples_are_mutual_best_wheels_and_metrics_count_them():
    classes = torch.tensor([[0, 1, 1, 1]])
    cand = torch.ones(1, 4, 4)
    s = torch.zeros(1, 4, 4)
    s[0, 1, 2] = s[0, 2, 1] = 0.9
    s[0, 2, 3] = s[0, 3, 2] = 0.8                 # wheel 3's best is 2, but 2 prefers 1
    couples = decode_couples(s, classes, cand, 0.5)
    assert couples[0].nonzero().tolist() == [[1, 2], [2, 1]]
    owner_t = torch.zeros(1, 4, 4, dtype=torch.uint8)
    owner_t[0, 0, 1] = owner_t[0, 1, 0] = owner_t[0, 0, 2] = owner_t[0, 2, 0] = 1
    pred = torch.zeros(1, 4, 4, dtype=torch.bool)
    pred[0, 1, 0] = True                           # wheel 1 right, wheel 2 missed, wheel 3 (no owner) right
    couple_t = torch.zeros(1, 4, 4, dtype=torch.uint8)
    couple_t[0, 1, 2] = couple_t[0, 2, 1] = 1
    every_wheel = torch.ones(1, 4, dtype=torch.bool)
    counts = relation_counts(pred, owner_t, couples, couple_t, classes, every_wheel)
    m = metrics_from_counts({k: float(v) for k, v in counts.items()})
    assert m["wheel_acc"] == pytest.approx(200 / 3) and m["image_acc"] == 0.0
    assert m["pair_precision"] == 100.0 and m["pair_recall"] == 50.0 and m["couple_f1"] == 100.0
    assert np.isclose(m["pair_f1"], 200 / 3)
    # wheel 2 (owned, missed) not evaluated (under eval.min_box_px): not counted, the image is right
    evaluated = torch.tensor([[True, True, False, True]])
    counts = relation_counts(pred, owner_t, couples, couple_t, classes, evaluated)
    m = metrics_from_counts({k: float(v) for k, v in counts.items()})
    assert counts["wheels"] == 2 and m["wheel_acc"] == 100.0 and m["image_acc"] == 100.0
    assert m["pair_recall"] == 100.0 and counts["couple_tp"] + counts["couple_fn"] == 0  # couple (1, 2) is out too


def test_role_counts_score_each_known_wheel_and_each_front_rear_couple_order():
    # wheels 1 (front) and 2 (rear) are a couple; wheel 3 is a front wheel alone; wheel 4 has no known role;
    # wheel 5 is padding (not valid)
    role = torch.tensor([[-1, 1, 0, 1, -1, 0]])
    valid = torch.tensor([[1, 1, 1, 1, 1, 0]])
    couple = torch.zeros(1, 6, 6)
    couple[0, 1, 2] = couple[0, 2, 1] = 1
    front = torch.tensor([[0.5, 0.45, 0.40, 0.7, 0.9, 0.9]])  # wheel 1 below 0.5 (wrong) but above its rear (order right)
    c = role_counts(front, role, valid, couple)
    assert {k: int(v) for k, v in c.items()} == {"role_right": 2, "role_known": 3, "order_right": 1, "order_known": 1}
    assert role_percentages({k: float(v) for k, v in c.items()}) == {"role_acc": pytest.approx(200 / 3),
                                                                     "order_acc": 100.0}
    front[0, 2] = 0.6                               # the rear wheel now above the front one: the order is wrong
    assert int(role_counts(front, role, valid, couple)["order_right"]) == 0
    no_roles = role_counts(front, torch.full_like(role, -1), valid, couple)
    assert role_percentages({k: float(v) for k, v in no_roles.items()}) == {}


def test_pair_geometry_gives_edge_offsets_size_ratios_and_containment():
    vehicle, wheel = [0.2, 0.2, 0.6, 0.6], [0.25, 0.5, 0.35, 0.6]  # the wheel in the vehicle's lower left
    g = pair_geometry(torch.tensor([[vehicle, wheel]]))[0]
    assert g.shape == (2, 2, EDGE_FEATURES) == (2, 2, 8)
    left, top, right, bottom, log_w, log_h, in_i, in_j = g[0, 1].tolist()   # the wheel seen from the vehicle
    assert [left, top, right, bottom] == pytest.approx([0.125, 0.75, -0.625, 0.0])  # bottoms level
    assert log_w == pytest.approx(np.log(0.25)) and log_h == pytest.approx(np.log(0.25))
    assert in_i == pytest.approx(0.01 / 0.16) and in_j == pytest.approx(1.0)
    assert g[1, 0, :4].tolist() == pytest.approx([-0.5, -3.0, 2.5, 0.0])      # the vehicle seen from the wheel
    assert torch.allclose(g[1, 0, 6:], g[0, 1, 6:].flip(0)) and torch.allclose(g[0, 0, :6], torch.zeros(6))


def test_pair_geometry_is_finite_for_padding_and_clamped():
    boxes = torch.tensor([[[0.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.9, 0.9], [0.5, 0.5, 0.5001, 0.5001]]])
    g = pair_geometry(boxes)
    assert torch.isfinite(g).all() and g[..., :4].abs().max() <= 10 and g[..., 4:6].abs().max() <= 5


def test_edge_geometry_is_an_opt_in_addition_the_attention_reads():
    assert _net().attention.fc1.in_features == 2 * 32                     # the paper's Net(x_i, x_j)
    net = _net(edge_geometry=True)
    assert net.attention.fc1.in_features == 2 * 32 + EDGE_FEATURES
    x, adj, _, _ = _inputs(12)
    h = net.embed(x)
    moved = x[:, :, 3:, 0, 0].clone()
    moved[:, 0] += 0.1                                                      # the same node features, box moved
    with torch.no_grad():
        _, scale = net.edge_weights(h, adj, pair_geometry(x[:, :, 3:, 0, 0]))
        _, scale_moved = net.edge_weights(h, adj, pair_geometry(moved))
    assert not torch.allclose(scale, scale_moved)
    with pytest.raises(ValueError, match="pair geometry"):
        net.edge_weights(h, adj)


def test_geometry_gate_is_an_opt_in_symmetric_gate_on_the_ownership_cosines():
    assert _net().gate is None and _net(edge_geometry=True).gate is None
    net = _net(geometry_gate=True)
    x, adj, cand, _ = _inputs(12)
    coords = x[:, :, 3:, 0, 0]
    gate = net.gate(pair_geometry(coords))
    assert torch.all((gate > 0) & (gate < 1)) and torch.allclose(gate, gate.transpose(1, 2))
    h = net.embed(x)
    moved = coords.clone()
    moved[:, 0] += 0.1                                                      # the same node features, box moved
    with torch.no_grad():
        owner, couple, _ = net.relate(h, adj, cand, coords)
        owner_moved, couple_moved, _ = net.relate(h, adj, cand, moved)
        plain = _net()
        plain.load_state_dict({k: v for k, v in net.state_dict().items() if not k.startswith("gate.")})
        owner_plain = plain.relate(h, adj, cand, coords)[0]
    assert not torch.allclose(owner, owner_moved) and torch.equal(couple, couple_moved)  # gates ownership only
    assert torch.allclose(owner, owner_plain * gate, atol=1e-6)            # cosine x gate
    with pytest.raises(ValueError, match="coords"):
        net.relate(h, adj, cand)


def test_ensemble_decides_on_the_mean_of_its_members_scores():
    from stages.relation.model import RelationEnsemble

    cfg = ModelConfig(backbone=conv_fc(16), hidden=16, embed_dim=8, gat_hidden=8)
    members = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        members.append(RelationNet(cfg).eval())
    ensemble = RelationEnsemble(members).eval()
    gen = torch.Generator().manual_seed(3)
    x = torch.rand((2, 5, 7, 16, 16), generator=gen)
    adj, cand = torch.rand((2, 5, 5), generator=gen), torch.ones((2, 5, 5))
    with torch.no_grad():
        alone = [m(x, adj, cand) for m in members]
        together = ensemble(x, adj, cand)
    assert ensemble.cfg == cfg and count_parameters(ensemble) == 2 * count_parameters(members[0])
    for k in range(3):  # owner, couple, front
        torch.testing.assert_close(together[k], (alone[0][k] + alone[1][k]) / 2)
        assert not torch.allclose(together[k], alone[0][k])
    with pytest.raises(ValueError, match="differ in configuration"):
        RelationEnsemble([members[0], RelationNet(ModelConfig(backbone=conv_fc(16), hidden=8))])
    with pytest.raises(ValueError, match="at least one"):
        RelationEnsemble([])


def test_a_relation_json_from_before_the_backbone_named_its_class_loads(tmp_path):
    """relation.json named its backbone ``backbone: resnet18`` beside input_size, expansion and base_width."""
    import json

    from stages.relation.stage import load_network

    net = _net(backbone={"_target_": RESNET18, "input_size": 16, "base_width": 8})
    torch.save(net.state_dict(), tmp_path / "relation.pt")
    old = {"backbone": "resnet18", "input_size": 16, "expansion": 1, "base_width": 8, "hidden": 32, "embed_dim": 16,
           "gat": True, "gat_hidden": 16, "gcn_layers": 2, "edge_geometry": False, "geometry_gate": False}
    (tmp_path / "relation.json").write_text(json.dumps({"model": old}))
    loaded, _ = load_network(tmp_path)
    assert loaded.cfg == net.cfg
    x, adj, cand, _ = _inputs(12)
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(net(x, adj, cand), loaded(x, adj, cand), strict=True))
