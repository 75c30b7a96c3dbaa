import pytest
import torch

from stages.detector.heads import HEATMAP_EPS
from stages.detector.model import CenterNetWithDecode, build_centernet, load_detector, save_detector

TINY = {"_target_": "stages.detector.backbones.TinyBackbone", "channels": [8, 8, 16, 16], "out_channels": 16}
RESNET18 = {"_target_": "stages.detector.backbones.ResNet18Deconv", "deconv_channels": [256, 256, 256]}


def config(backbone: dict, width: int = 64, height: int = 32, regression: str = "centernet",
           head_conv: int = 16) -> dict:
    return {"backbone": backbone, "head_conv": head_conv, "class_names": ["vehicle", "wheel"],
            "input_width": width, "input_height": height, "down_ratio": 4, "max_detections": 7,
            "score_threshold": 0.1, "regression": regression}


@pytest.mark.parametrize("backbone", [TINY, RESNET18], ids=["tiny", "resnet18"])
def test_output_shapes_stride_4(backbone):
    net = build_centernet(config(backbone)).eval()
    with torch.no_grad():
        heat, wh, reg = net(torch.randn(2, 3, 32, 64))
    assert heat.shape == (2, 2, 8, 16) and wh.shape == (2, 2, 8, 16) and reg.shape == (2, 2, 8, 16)
    assert heat.min() >= HEATMAP_EPS and heat.max() <= 1 - HEATMAP_EPS
    # heatmap bias -2.19: an untrained network starts near the prior probability 0.1
    assert heat.mean().item() == pytest.approx(0.1, abs=0.05)


def test_resnet18_has_resnet18_size():
    net = build_centernet(config(RESNET18))
    backbone_params = sum(p.numel() for n, p in net.backbone.named_parameters() if not n.startswith("deconv"))
    assert backbone_params == pytest.approx(11.18e6, rel=0.01)  # ResNet-18 without its fc layer


def test_default_tiny_config_reaches_stride_32():
    from pathlib import Path

    from omegaconf import OmegaConf

    tiny = OmegaConf.to_container(OmegaConf.load(Path(__file__).resolve().parents[3] / "conf/detector/backbone/tiny.yaml"))["backbone"]
    net = build_centernet(config(tiny, width=96, height=64)).eval()
    assert net.backbone.stride_multiple == 32
    with torch.no_grad():
        assert net(torch.randn(1, 3, 64, 96))[0].shape == (1, 2, 16, 24)
    with pytest.raises(ValueError, match="divisible by 32"):
        build_centernet(config(tiny, width=80))


def test_input_size_must_fit_the_strides():
    with pytest.raises(ValueError, match="divisible by 32"):
        build_centernet(config(RESNET18, width=80))
    with pytest.raises(ValueError, match="unknown backbone"):
        build_centernet(config({"name": "vgg", "head_conv": 8}))
    with pytest.raises(ValueError, match="cannot import"):
        build_centernet(config({"_target_": "stages.detector.backbones.VGG"}))
    with pytest.raises(TypeError, match="not a torch nn.Module"):
        build_centernet(config({"_target_": "stages.detector.backbones.build_backbone"}))
    with pytest.raises(TypeError, match="does not take"):
        build_centernet(config(dict(TINY, expansion=4)))


def test_a_model_json_from_before_target_loads(tmp_path):
    """model.json named its backbone ``name: tiny`` with the heads' ``head_conv`` among the backbone's fields."""
    net = build_centernet(config(TINY)).eval()
    old = config({"name": "tiny", "channels": [8, 8, 16, 16], "out_channels": 16, "head_conv": 16})
    save_detector(tmp_path, net, old)
    loaded, _ = load_detector(tmp_path)
    x = torch.randn(1, 3, 32, 64)
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(net(x), loaded(x), strict=True))


def test_save_load_round_trip_and_decoding_wrapper(tmp_path):
    net = build_centernet(config(TINY)).eval()
    save_detector(tmp_path, net, config(TINY))
    loaded, cfg = load_detector(tmp_path)
    x = torch.randn(3, 3, 32, 64)
    with torch.no_grad():
        for a, b in zip(net(x), loaded(x), strict=True):
            assert torch.equal(a, b)
        detections = CenterNetWithDecode(loaded, k=cfg["max_detections"])(x)
    assert detections.shape == (3, 7, 6)


def test_ttfnet_heads_give_non_negative_side_distances_and_old_configs_load_as_centernet(tmp_path):
    net = build_centernet(config(TINY, regression="ttfnet")).eval()
    with torch.no_grad():
        heat, ltrb = net(torch.randn(2, 3, 32, 64))
    assert heat.shape == (2, 2, 8, 16) and ltrb.shape == (2, 4, 8, 16)
    # ReLU x 16 px from a bias of 1: an untrained network starts with 32 px boxes, none negative
    assert ltrb.min() >= 0 and ltrb.mean().item() == pytest.approx(16.0, rel=0.1)
    assert CenterNetWithDecode(net, k=5)(torch.randn(1, 3, 32, 64)).shape == (1, 5, 6)
    old = config(TINY)
    del old["regression"]   # a model.json written before the choice existed
    save_detector(tmp_path, build_centernet(old), old)
    assert len(load_detector(tmp_path)[0](torch.randn(1, 3, 32, 64))) == 3
    with pytest.raises(ValueError, match="detector.regression"):
        build_centernet(config(TINY, regression="fcos"))


def test_tiny_backbone_blocks_per_stride():
    deeper = dict(TINY, blocks=[1, 2, 2])
    net = build_centernet(config(deeper)).eval()
    assert [len(stage) if isinstance(stage, torch.nn.Sequential) else 1 for stage in net.backbone.stages] == [1, 2, 2]
    with torch.no_grad():
        assert net(torch.randn(1, 3, 32, 64))[0].shape == (1, 2, 8, 16)
    # one block per stride keeps the weight names of models saved before `blocks` existed
    assert set(build_centernet(config(dict(TINY, blocks=[1, 1, 1]))).state_dict()) == set(build_centernet(config(TINY)).state_dict())
    with pytest.raises(ValueError, match="detector.backbone.blocks"):
        build_centernet(config(dict(TINY, blocks=[1, 2])))
