import math

import pytest
import torch

from stages.detector.losses import centernet_loss, focal_loss, reg_l1_loss


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
