import pytest
import torch
from torch import nn

from stages.training.memory_format import nhwc_unsafe_convolutions, use_channels_last


def shortcut_net(stem: int) -> nn.Module:
    """A stem and a residual shortcut that halves the resolution: the 1x1 stride-2 convolution of the crash."""
    return nn.Sequential(nn.Conv2d(3, stem, 3, padding=1), nn.ReLU(), nn.Conv2d(stem, 2 * stem, 1, stride=2))


@pytest.mark.parametrize(("stem", "unsafe"), [(1, False), (4, True), (8, True), (12, True), (16, False), (24, False)])
def test_the_strided_one_by_one_convolution_behind_a_narrow_stem_is_unsafe(stem, unsafe):
    assert nhwc_unsafe_convolutions(shortcut_net(stem)) == (["2"] if unsafe else [])


def test_other_narrow_convolutions_are_safe():
    net = nn.Sequential(nn.Conv2d(8, 16, 1), nn.Conv2d(16, 8, 3, stride=2, padding=1), nn.Conv2d(8, 8, 3, padding=1))
    assert nhwc_unsafe_convolutions(net) == []


def test_the_rule():
    safe, unsafe = shortcut_net(16), shortcut_net(8)
    assert not use_channels_last(False, safe, bf16=True, on_gpu=False, what="net")   # not asked for
    assert use_channels_last(True, safe, bf16=False, on_gpu=False, what="net")        # fp32 on a CPU, safe
    assert not use_channels_last(True, unsafe, bf16=False, on_gpu=False, what="net")  # fp32 on a CPU, unsafe
    assert use_channels_last(True, unsafe, bf16=True, on_gpu=False, what="net")       # bf16 kernels run every width
    assert use_channels_last(True, safe, bf16=True, on_gpu=True, what="net")
    assert not use_channels_last(True, safe, bf16=False, on_gpu=True, what="net")     # fp32 on a GPU: not measured


def test_the_default_networks_train_channels_last_in_fp32_on_a_cpu():
    from omegaconf import OmegaConf

    from benchmarks.bench_latency import default_configs
    from stages.detector.model import build_centernet, model_config
    from stages.facing.model import FacingNet
    from stages.relation.model import ModelConfig, RelationNet

    rel, det = default_configs()
    facing = OmegaConf.load("conf/facing/default.yaml")
    for net in (build_centernet(model_config(det)), RelationNet(ModelConfig.from_cfg(OmegaConf.create(rel))).backbone,
                FacingNet(tuple(facing.widths), int(facing.hidden))):
        assert nhwc_unsafe_convolutions(net) == []
    assert OmegaConf.load("conf/relation/default.yaml").train.channels_last and facing.train.channels_last


def test_a_channels_last_step_computes_what_nchw_does():
    torch.manual_seed(0)
    nchw = shortcut_net(16)
    nhwc = shortcut_net(16)
    nhwc.load_state_dict(nchw.state_dict())
    nhwc = nhwc.to(memory_format=torch.channels_last)
    x = torch.randn(2, 3, 32, 32)
    nchw(x).square().mean().backward()
    nhwc(x.contiguous(memory_format=torch.channels_last)).square().mean().backward()
    for a, b in zip(nchw.parameters(), nhwc.parameters(), strict=True):
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-6)


def test_a_network_built_to_answer_leaves_the_seeded_draw_alone():
    torch.manual_seed(7)
    want = nn.Linear(4, 4).weight.detach().clone()   # what a stage seeded with 7 builds first
    for bf16 in (False, True):
        built = []
        torch.manual_seed(7)
        assert use_channels_last(True, lambda built=built: built.append(1) or shortcut_net(16), bf16=bf16,
                                 on_gpu=False, what="n")
        assert built == ([] if bf16 else [1])         # built only when the answer needs it
        assert torch.equal(nn.Linear(4, 4).weight, want)
    torch.manual_seed(7)
    assert not use_channels_last(True, lambda: shortcut_net(8), bf16=False, on_gpu=False, what="n")
    assert torch.equal(nn.Linear(4, 4).weight, want)
