import math

import pytest
import torch

from stages.detector.losses import (
    centernet_loss,
    detector_loss,
    focal_loss,
    generalized_iou,
    giou_box_loss,
    reg_l1_loss,
)


def test_focal_loss_hand_computed():
    gt = torch.tensor([[[[1.0, 0.5], [0.0, 0.0]]]])
    pred = torch.tensor([[[[0.8, 0.3], [0.1, 0.6]]]])
    pos = -(0.2 ** 2) * math.log(0.8)                      # (1 - p)^2 log p at the peak
    neg = -(0.5 ** 4) * 0.3 ** 2 * math.log(0.7)           # (1 - gt)^4 p^2 log(1 - p)
    neg += -(0.1 ** 2) * math.log(0.9) - (0.6 ** 2) * math.log(0.4)
    assert focal_loss(pred, gt).item() == pytest.approx(pos + neg, rel=1e-5)
    assert focal_loss(pred, gt).item() == pytest.approx(0.3418504, rel=1e-5)
    # normalised by the number of peaks: a second identical image doubles numerator and count
    assert focal_loss(pred.repeat(2, 1, 1, 1), gt.repeat(2, 1, 1, 1)).item() == pytest.approx(pos + neg, rel=1e-5)
    # with no peak at all only the negative term remains, unnormalised
    no_peak = torch.zeros_like(gt)
    expected = -sum(p ** 2 * math.log(1 - p) for p in (0.8, 0.3, 0.1, 0.6))
    assert focal_loss(pred, no_peak).item() == pytest.approx(expected, rel=1e-5)


def test_reg_l1_loss_reads_object_cells_only():
    out = torch.zeros(1, 2, 2, 3)
    out[0, :, 1, 2] = torch.tensor([3.0, 4.0])   # cell y=1, x=2 -> flat index 5
    target = torch.tensor([[[2.0, 6.0], [9.0, 9.0]]])
    ind = torch.tensor([[5, 0]])
    mask = torch.tensor([[1.0, 0.0]])              # the second object is padding
    assert reg_l1_loss(out, mask, ind, target).item() == pytest.approx((1 + 2) / 2, rel=1e-3)


def test_centernet_loss_weights_size_by_a_tenth():
    heat = torch.full((1, 2, 2, 2), 0.5)
    wh = torch.zeros(1, 2, 2, 2)
    reg = torch.zeros(1, 2, 2, 2)
    batch = {"hm": torch.zeros(1, 2, 2, 2), "mask": torch.ones(1, 1), "ind": torch.zeros(1, 1, dtype=torch.long),
             "wh": torch.tensor([[[4.0, 2.0]]]), "reg": torch.tensor([[[0.5, 0.5]]])}
    batch["hm"][0, 0, 0, 0] = 1.0
    total, parts = centernet_loss((heat, wh, reg), batch)
    assert parts["wh"].item() == pytest.approx(3.0, rel=1e-3) and parts["off"].item() == pytest.approx(0.5, rel=1e-3)
    assert total.item() == pytest.approx(parts["hm"].item() + 0.1 * 3.0 + 0.5, rel=1e-3)


def test_generalized_iou_hand_computed():
    a = torch.tensor([0.0, 0.0, 2.0, 2.0])
    assert generalized_iou(a, a).item() == pytest.approx(1.0, abs=1e-5)
    # half overlapping: IoU 2/6, enclosing 3 x 2 = 6 = the union, so GIoU = IoU
    assert generalized_iou(a, torch.tensor([1.0, 0.0, 3.0, 2.0])).item() == pytest.approx(2 / 6, abs=1e-5)
    # apart: IoU 0, enclosing 6 x 2 = 12, union 8 -> GIoU = -(12 - 8) / 12; farther apart is worse
    far = generalized_iou(a, torch.tensor([4.0, 0.0, 6.0, 2.0])).item()
    assert far == pytest.approx(-(12 - 8) / 12, abs=1e-5) and far < generalized_iou(a, torch.tensor([2.0, 0.0, 4.0, 2.0]))


def test_giou_box_loss_is_weighted_over_sample_cells_and_has_a_gradient_apart():
    # one sample cell (y=0, x=1: centre (6, 2) at stride 4) whose target box is (4, 0, 8, 4)
    target = torch.zeros(1, 4, 1, 3)
    target[0, :, 0, 1] = torch.tensor([4.0, 0.0, 8.0, 4.0])
    weight = torch.zeros(1, 1, 3)
    weight[0, 0, 1] = 2.0
    perfect = torch.zeros(1, 4, 1, 3)
    perfect[0, :, 0, 1] = torch.tensor([2.0, 2.0, 2.0, 2.0])
    assert giou_box_loss(perfect, target, weight, 4).item() == pytest.approx(0.0, abs=1e-5)
    # predictions at cells of weight 0 do not count
    elsewhere = perfect.clone()
    elsewhere[0, :, 0, 0] = 50.0
    assert giou_box_loss(elsewhere, target, weight, 4).item() == pytest.approx(0.0, abs=1e-5)
    # a box far to the right of its target (IoU 0) still gets a gradient pulling it back
    away = torch.zeros(1, 4, 1, 3)
    away[0, :, 0, 1] = torch.tensor([-10.0, 2.0, 14.0, 2.0])   # (16, 0, 20, 4)
    away.requires_grad_(True)
    loss = giou_box_loss(away, target, weight, 4)
    loss.backward()
    assert loss.item() > 1.0 and away.grad.abs().sum() > 0
    # no sample cell in the batch: zero, still differentiable
    assert giou_box_loss(away, target, torch.zeros_like(weight), 4).item() == 0.0


def test_detector_loss_dispatches_on_the_regression_and_refuses_unknown_ones():
    heat = torch.full((1, 2, 1, 3), 0.1)
    batch = {"hm": torch.zeros(1, 2, 1, 3), "box": torch.zeros(1, 4, 1, 3), "box_weight": torch.zeros(1, 1, 3)}
    total, parts = detector_loss((heat, torch.zeros(1, 4, 1, 3)), batch, "ttfnet", 4, {"hm_weight": 1.0})
    assert set(parts) == {"hm", "giou"} and total.item() == pytest.approx(parts["hm"].item())
    with pytest.raises(ValueError, match="detector.regression"):
        detector_loss((heat,), batch, "fcos", 4, {})
