"""Lens augmentation of the relation boxes: identity at k = 0, one-to-one (nesting and order kept), edge
fixed, centre scaled by 1 - k, seeded, off by default, and wired into the training dataset only."""

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from deepword.relation_graph import InputConfig
from stages.relation.lightning import GraphDataset
from stages.relation.warp import BoxWarpConfig, radial_warp, random_box_warp, warp_boxes
from tests.stages.relation.relation_data import records, split

CONF = Path(__file__).resolve().parents[3] / "conf" / "relation" / "default.yaml"


def random_boxes(n=200, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * 0.8
    wh = 0.01 + torch.rand(n, 2, generator=g) * 0.19
    return torch.cat([xy, (xy + wh).clamp(max=1.0)], -1)


def test_zero_distortion_is_the_identity():
    boxes = random_boxes()
    assert torch.allclose(warp_boxes(boxes, 0.0, (0.5, 0.5)), boxes, atol=1e-6)


def test_edge_of_the_field_of_view_stays_and_the_centre_scales_by_one_minus_k():
    k = 0.15
    edge = torch.tensor([[0.0, 0.5], [1.0, 0.5], [0.5, 0.0], [0.5, 1.0]])
    assert torch.allclose(radial_warp(edge, k, (0.5, 0.5)), edge, atol=1e-6)
    near = torch.tensor([[0.51, 0.5]])
    moved = radial_warp(near, k, (0.5, 0.5))
    assert moved[0, 0] - 0.5 == pytest.approx(0.01 * (1 - k), rel=1e-3)


@pytest.mark.parametrize("k", [-0.19, -0.1, 0.1, 0.19])
def test_the_warp_keeps_nesting_and_left_to_right_order(k):
    """A wheel box inside its vehicle's box stays inside, and of two boxes side by side the left one stays
    left: what the relations, couples and roles depend on, which the warp therefore leaves as they are."""
    outer = random_boxes(300, seed=1)
    w, h = outer[:, 2] - outer[:, 0], outer[:, 3] - outer[:, 1]
    inner = torch.stack([outer[:, 0] + 0.2 * w, outer[:, 1] + 0.6 * h, outer[:, 0] + 0.4 * w, outer[:, 3]], -1)
    centre = (0.47, 0.53)
    wo, wi = warp_boxes(outer, k, centre), warp_boxes(inner, k, centre)
    tol = 1e-3  # the bound of SAMPLES boundary points may fall short of the true extremum by this little
    assert (wi[:, :2] >= wo[:, :2] - tol).all() and (wi[:, 2:] <= wo[:, 2:] + tol).all()
    assert (wo[:, 2:] > wo[:, :2]).all() and (wo > -0.1).all() and (wo < 1.1).all()
    left = torch.tensor([[0.1, 0.4, 0.2, 0.5]])
    right = torch.tensor([[0.3, 0.4, 0.4, 0.5]])
    assert warp_boxes(left, k, centre)[0, 2] < warp_boxes(right, k, centre)[0, 0]


def test_the_warp_changes_box_geometry_beyond_a_scaling():
    """It must change what the pair geometry sees (relative sizes), or it would teach nothing: the
    normalised coordinates are already invariant to image size and aspect."""
    boxes = torch.tensor([[0.45, 0.45, 0.55, 0.55], [0.05, 0.45, 0.15, 0.55]])
    warped = warp_boxes(boxes, 0.15, (0.5, 0.5))
    width = warped[:, 2] - warped[:, 0]
    assert (width[1] / width[0]).item() > 1.1  # the centre box shrank, the one near the edge grew


def test_random_warp_is_seeded_and_off_by_default():
    boxes = random_boxes(20)
    cfg = BoxWarpConfig(prob=1.0, radial=0.15, centre=0.05)
    torch.manual_seed(3)
    a = random_box_warp(boxes, cfg)
    torch.manual_seed(3)
    b = random_box_warp(boxes, cfg)
    assert torch.equal(a, b) and not torch.equal(a, boxes)
    default = BoxWarpConfig.from_cfg(OmegaConf.to_container(OmegaConf.load(CONF)).get("box_warp"))
    assert isinstance(default, BoxWarpConfig)
    assert random_box_warp(boxes, BoxWarpConfig(prob=0.0)) is boxes


def test_config_is_validated():
    with pytest.raises(ValueError, match="one-to-one"):
        BoxWarpConfig(prob=1.0, radial=0.3)
    with pytest.raises(ValueError, match="unknown fields"):
        BoxWarpConfig.from_cfg({"prob": 0.5, "radius": 0.1})


def test_training_dataset_warps_boxes_and_keeps_targets():
    data = split(records(6), InputConfig(input_size=16, max_objects=16))
    plain = GraphDataset(data)
    warped = GraphDataset(data, box_warp=BoxWarpConfig(prob=1.0, radial=0.19, centre=0.0))
    torch.manual_seed(0)
    changed = 0
    for i in range(len(data)):
        a, b = plain[i], warped[i]
        for key in ("owner", "couple", "role", "classes", "cand", "adj", "crops"):
            assert torch.equal(a[key], b[key]), key
        changed += int(not torch.allclose(a["coords"], b["coords"]))
    assert changed > 0
