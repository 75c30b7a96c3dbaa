"""Appearance augmentation of the relation crops: seeded, shape- and geometry-preserving, configurable."""

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from stages.relation.augment import AugmentConfig, augment_crops

CONF = Path(__file__).resolve().parents[3] / "conf" / "relation" / "default.yaml"


def configured(**changes) -> AugmentConfig:
    aug = OmegaConf.to_container(OmegaConf.load(CONF).augment)
    return AugmentConfig.from_cfg(aug | changes)


def sample_crops(n=12, size=24) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return torch.randint(0, 256, (n, 3, size, size), generator=g, dtype=torch.uint8)


def test_probability_zero_leaves_crops_untouched():
    crops = sample_crops()
    assert augment_crops(crops, configured(prob=0.0)) is crops


def test_augmentation_is_seeded_and_keeps_shape_and_dtype():
    crops = sample_crops()
    cfg = configured(prob=1.0)
    torch.manual_seed(5)
    a = augment_crops(crops, cfg)
    torch.manual_seed(5)
    b = augment_crops(crops, cfg)
    torch.manual_seed(6)
    c = augment_crops(crops, cfg)
    assert a.shape == crops.shape and a.dtype == torch.uint8
    assert torch.equal(a, b) and not torch.equal(a, c) and not torch.equal(a, crops)


def test_each_effect_alone_changes_the_crops():
    crops = sample_crops()
    effects = {"brightness": {"brightness": 0.5}, "grayscale": {"grayscale": 1.0}, "blur": {"blur_prob": 1.0},
               "noise": {"noise_prob": 1.0}, "jpeg": {"jpeg_prob": 1.0, "jpeg_quality": [20, 20]},
               "scale": {"scale": [1.3, 1.3]}, "stretch": {"stretch": 0.3}, "hue": {"hue": 0.5}, "drop": {"drop_pixels": 1.0}}
    for name, change in effects.items():
        cfg = AugmentConfig(prob=1.0, **{k: tuple(v) if isinstance(v, list) else v for k, v in change.items()})
        torch.manual_seed(0)
        out = augment_crops(crops, cfg)
        assert not torch.equal(out, crops), name
    grey = augment_crops(crops, AugmentConfig(prob=1.0, grayscale=1.0))
    assert torch.equal(grey[:, 0], grey[:, 1]) and torch.equal(grey[:, 1], grey[:, 2])
    assert not augment_crops(crops, AugmentConfig(prob=1.0, drop_pixels=1.0)).any()


def test_crops_blurred_together_are_the_crops_blurred_one_at_a_time():
    """The grouped blur (crops of one kernel radius in one convolution) computes what a convolution per crop does,
    to the bit: the augmentation's output and random stream are those of blurring each crop on its own."""
    import torch.nn.functional as F

    from stages.relation.augment import _gaussian_blur, _gaussian_kernel

    def one_crop(x, sigma):   # the definition: one crop's separable blur, edges replicated
        k = _gaussian_kernel(sigma, x.dtype)
        r, c = len(k) // 2, x.shape[1]
        x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
        return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)

    g = torch.Generator().manual_seed(4)
    x = 255 * torch.rand(9, 3, 20, 24, generator=g)
    sigmas = [0.4, 1.4, 0.6, 1.5, 0.45, 1.0, 0.9, 1.2, 0.5]   # radii 1, 3 and 2, interleaved
    together = _gaussian_blur(x, sigmas)
    assert len({len(_gaussian_kernel(s, x.dtype)) for s in sigmas}) == 3
    for i, sigma in enumerate(sigmas):
        assert torch.equal(together[i:i + 1], one_crop(x[i:i + 1], sigma)), i


def test_the_zoom_grid_is_affine_grids_to_the_bit():
    import torch.nn.functional as F

    from stages.relation.augment import _zoom_grid

    g = torch.Generator().manual_seed(5)
    sx, sy = 0.8 + 0.4 * torch.rand(6, generator=g), 0.8 + 0.4 * torch.rand(6, generator=g)
    theta = torch.zeros(6, 2, 3)
    theta[:, 0, 0], theta[:, 1, 1] = sx, sy
    assert torch.equal(_zoom_grid(sx, sy, 20, 24), F.affine_grid(theta, [6, 3, 20, 24], align_corners=False))


def test_a_bad_augment_config_names_the_field():
    with pytest.raises(ValueError, match="relation.augment.grayscale"):
        configured(grayscale=1.5)
    with pytest.raises(ValueError, match="relation.augment.hue"):
        configured(hue=0.7)
    with pytest.raises(ValueError, match="unknown fields \\['tint'\\]"):
        configured(tint=0.1)


def test_training_graphs_keep_their_geometry_when_augmented():
    from deepword.relation_graph import InputConfig
    from stages.relation.lightning import GraphDataset
    from tests.stages.relation.relation_data import records, split

    split = split(records(3), InputConfig(input_size=16, max_objects=32))
    torch.manual_seed(1)
    plain, augmented = GraphDataset(split), GraphDataset(split, augment=configured(prob=1.0))
    a, b = plain[0], augmented[0]
    for key in a:
        if key != "crops":
            assert torch.equal(a[key], b[key]), key
    assert a["crops"].shape == b["crops"].shape and not torch.equal(a["crops"], b["crops"])


def test_stretch_keeps_the_box_centred_and_changes_its_aspect():
    """The anisotropic zoom is about the crop centre (where the box is): a centred square stays centred and
    becomes a rectangle, wider than high or higher than wide."""
    crops = torch.zeros(16, 3, 24, 24, dtype=torch.uint8)
    crops[:, :, 8:16, 8:16] = 255
    torch.manual_seed(0)
    out = augment_crops(crops, AugmentConfig(prob=1.0, stretch=0.4)).float().mean(1)
    grid = torch.arange(24, dtype=torch.float32) + 0.5
    mass = out.sum((1, 2))
    cx = (out.sum(1) * grid).sum(1) / mass
    cy = (out.sum(2) * grid).sum(1) / mass
    assert torch.allclose(cx, torch.full_like(cx, 12.0), atol=0.3) and torch.allclose(cy, torch.full_like(cy, 12.0), atol=0.3)
    width = (out.max(1).values > 127).sum(1)
    height = (out.max(2).values > 127).sum(1)
    assert (width != height).any()


def test_hue_turns_colours_but_keeps_greys_and_luma():
    crops = sample_crops()
    grey = crops[:, :1].expand(-1, 3, -1, -1).contiguous()
    cfg = AugmentConfig(prob=1.0, hue=0.5)
    torch.manual_seed(0)
    assert torch.equal(augment_crops(grey, cfg), grey)      # a grey crop has no hue to turn
    torch.manual_seed(0)
    turned = augment_crops(crops, cfg).float()
    luma = torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
    inside = ((turned > 0) & (turned < 255)).all(1, keepdim=True)   # away from the clamp, the brightness stays
    difference = ((turned * luma).sum(1, keepdim=True) - (crops.float() * luma).sum(1, keepdim=True))[inside]
    assert difference.abs().max() <= 1.0 and not torch.equal(turned, crops.float())
