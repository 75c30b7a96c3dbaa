import numpy as np
import torch

from stages.detector.decode import ctdet_decode, decode_outputs, nms_heatmap, ttfnet_decode
from stages.detector.heads import HEATMAP_EPS
from stages.detector.targets import centernet_targets, ttfnet_box_targets


def dense_maps(targets: dict, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What a perfect network would output: the target heatmap and size/offset written at object cells."""
    wh = np.zeros((2, height * width), dtype=np.float32)
    reg = np.zeros((2, height * width), dtype=np.float32)
    for k in np.flatnonzero(targets["mask"]):
        wh[:, targets["ind"][k]] = targets["wh"][k]
        reg[:, targets["ind"][k]] = targets["reg"][k]
    heat = np.clip(targets["hm"], HEATMAP_EPS, 1 - HEATMAP_EPS)
    as_tensor = lambda a: torch.from_numpy(a.reshape(1, -1, height, width))  # noqa: E731
    return as_tensor(heat), as_tensor(wh), as_tensor(reg)


# input-pixel boxes of two vehicles and three wheels (one wheel inside a vehicle box), stride 4, 64 x 32 cells
BOXES = np.array([[40.0, 30.0, 140.0, 90.0], [150.0, 20.0, 230.0, 70.0],
                  [50.0, 78.0, 66.0, 94.0], [118.0, 77.5, 133.0, 93.0], [200.0, 60.0, 212.0, 71.0]])
CLASSES = np.array([0, 0, 1, 1, 1])
W, H = 64, 32


def assert_finds_every_box_once(detections: np.ndarray) -> None:
    found = detections[detections[:, 4] > 0.5]
    assert len(found) == len(BOXES)
    for box, cls in zip(BOXES, CLASSES, strict=True):
        match = found[np.abs(found[:, :4] - box).max(axis=1) < 1e-3]
        assert len(match) == 1 and match[0, 5] == cls
    assert np.all(detections[len(BOXES):, 4] < 0.5)  # the rest are Gaussian shoulders or background


def test_decoding_rendered_targets_returns_the_boxes():
    t = centernet_targets(BOXES / 4, CLASSES, num_classes=2, out_width=W, out_height=H, max_objects=8)
    assert_finds_every_box_once(ctdet_decode(*dense_maps(t, W, H), k=10, down_ratio=4)[0].numpy())


def test_nms_keeps_only_local_maxima():
    heat = torch.zeros(1, 1, 5, 5)
    heat[0, 0, 2, 2], heat[0, 0, 2, 3], heat[0, 0, 0, 0] = 0.9, 0.7, 0.4
    kept = nms_heatmap(heat)
    assert kept[0, 0, 2, 2] == 0.9 and kept[0, 0, 0, 0] == 0.4 and kept[0, 0, 2, 3] == 0
    assert int((kept > 0).sum()) == 2


def test_decode_is_batched_and_sorted():
    heat = torch.rand(3, 2, 8, 8) * 0.5
    out = ctdet_decode(heat, torch.ones(3, 2, 8, 8), torch.zeros(3, 2, 8, 8), k=5)
    assert out.shape == (3, 5, 6)
    assert torch.all(out[:, :-1, 4] >= out[:, 1:, 4])
    assert torch.allclose(out[..., 2] - out[..., 0], torch.full((3, 5), 4.0))  # 1 cell wide at stride 4


def perfect_ltrb(box_targets: dict) -> torch.Tensor:
    """What a perfect TTFNet head would output: at every sample cell, the distances from the cell centre to
    its target box's sides (elsewhere 0)."""
    box, weight = box_targets["box"], box_targets["box_weight"]
    h, w = weight.shape
    cx, cy = (np.arange(w) + 0.5) * 4, (np.arange(h) + 0.5)[:, None] * 4
    ltrb = np.stack([cx - box[0], cy - box[1], box[2] - cx, box[3] - cy]) * (weight > 0)
    return torch.from_numpy(ltrb[None].astype(np.float32))


def test_ttfnet_decoding_of_rendered_targets_returns_the_boxes():
    t = centernet_targets(BOXES / 4, CLASSES, num_classes=2, out_width=W, out_height=H, max_objects=8)
    heat = torch.from_numpy(np.clip(t["hm"], HEATMAP_EPS, 1 - HEATMAP_EPS)[None])
    ltrb = perfect_ltrb(ttfnet_box_targets(BOXES, W, H, 4))
    detections = ttfnet_decode(heat, ltrb, k=10, down_ratio=4)
    assert_finds_every_box_once(detections[0].numpy())
    # decode_outputs tells the two regressions apart by their maps
    assert torch.equal(decode_outputs((heat, ltrb), k=10), detections)
