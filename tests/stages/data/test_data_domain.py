"""Domain randomisation and the cross-domain split: every family is drawn, held-out families stay out of
the training data, generation is deterministic per seed, labels stay consistent in the held-out domain."""

import re
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from deepword.word_format import VEHICLE, WHEEL
from stages.data.backdrop import draw_look
from stages.data.domain import AXES, DomainConfig
from stages.data.sensor import draw_sensor
from stages.data.synword import FrameGenerator, generate, scene_families
from stages.data.world import SceneSampler

CONF = str(Path(__file__).resolve().parents[3] / "conf")
OBJECT_AXES = ("bodies", "paints", "materials", "wheels", "props")
FRAME_AXES = {"skies": "sky", "grounds": "ground"}


@pytest.fixture(scope="module")
def domains():
    """The composed in-domain (data=synword) and held-out (shift) generator configs, small."""
    with initialize_config_dir(version_base="1.3", config_dir=CONF):
        cfg = compose("config", overrides=["profile=smoke"])
    train = OmegaConf.to_container(cfg.data, resolve=True)
    heldout = OmegaConf.to_container(cfg.shift.data, resolve=True)
    for d in (train, heldout):
        d.update(image_size=[160, 120], workers=1)
    return train, heldout


def held_out_axes(train: dict, heldout: dict) -> dict[str, set]:
    """The axes whose family lists differ between the two configs, with the held-out families."""
    return {axis: set(heldout["domain"][axis]) for axis in AXES if heldout["domain"][axis] != train["domain"][axis]}


def test_the_split_holds_out_bodies_skies_and_grounds_disjointly(domains):
    train, heldout = domains
    held = held_out_axes(train, heldout)
    assert {"bodies", "skies", "grounds"} <= set(held)
    for axis, families in held.items():
        assert not families & set(train["domain"][axis]), axis
    assert not set(heldout["lens"]["families"]) & set(train["lens"]["families"])
    assert heldout["stream"] != train["stream"]  # other scenes, not the training frames re-dressed


def test_every_family_appears_over_a_seeded_draw(domains):
    train, _ = domains
    everything = dict(train["domain"], **{axis: list(names) for axis, names in AXES.items()})
    domain = DomainConfig.from_cfg(everything)
    sampler = SceneSampler(train["scenes"], domain, 4.6, 1.84)
    seen = {axis: set() for axis in AXES}
    jpeg = set()
    rng = np.random.default_rng(0)
    for _ in range(60):
        families = scene_families(sampler.sample(rng))
        for axis in OBJECT_AXES:
            seen[axis] |= set(families[axis])
        look = draw_look(rng, domain.draw(rng, "skies"), domain.draw(rng, "grounds"), domain.sun_elevation_deg)
        seen["skies"].add(look.sky)
        seen["grounds"].add(look.ground)
        jpeg.add(draw_sensor(rng, domain.sensor).jpeg_quality > 0)
    assert seen == {axis: set(names) for axis, names in AXES.items()}
    assert jpeg == {True, False}


def test_no_held_out_family_appears_in_training_data_and_only_held_out_ones_in_the_held_out_set(domains, tmp_path):
    train, heldout = domains
    held = held_out_axes(train, heldout)
    for cfg, name in ((train, "train"), (heldout, "heldout")):
        records = generate(dict(cfg, frames=6), 3, tmp_path / name, workers=1, progress=False)
        assert records
        for rec in records:
            drawn = rec.extra["domain"]
            for axis, families in held.items():
                values = set(drawn[axis]) if axis in OBJECT_AXES else {drawn[FRAME_AXES[axis]]}
                if name == "train":
                    assert not values & families, (rec.image, axis, values)
                else:
                    assert values <= families, (rec.image, axis, values)
            lenses = set(cfg["lens"]["families"])
            assert rec.extra["calibration"]["intrinsic"]["model"] in lenses
            assert set(drawn["sensor"]) == {"noise_sigma", "blur_sigma", "exposure", "white_balance", "vignetting",
                                            "jpeg_quality"}


def test_held_out_generation_is_deterministic_per_seed_and_labels_consistent(domains):
    _, heldout = domains
    a, b, c = FrameGenerator(heldout, 5), FrameGenerator(heldout, 5), FrameGenerator(heldout, 6)
    fa, fb, fc = a.render_frame(1), b.render_frame(1), c.render_frame(1)
    for (_, img_a, rec_a), (_, img_b, rec_b) in zip(fa, fb, strict=True):
        assert rec_a.to_json() == rec_b.to_json() and img_a.tobytes() == img_b.tobytes()
    assert any(ra.to_json() != rc.to_json() for (_, _, ra), (_, _, rc) in zip(fa, fc, strict=True))
    for frame in range(4):
        for _, img, rec in a.render_frame(frame):
            assert img.shape == (rec.height, rec.width, 3)
            ids = set(rec.box_ids.tolist())
            cls = dict(zip(rec.box_ids.tolist(), rec.class_ids.tolist(), strict=True))
            xyxy = rec.xyxy
            assert (xyxy[:, :2] >= 0).all() and (xyxy[:, 2] <= rec.width).all() and (xyxy[:, 3] <= rec.height).all()
            assert (xyxy[:, 2] > xyxy[:, 0]).all() and (xyxy[:, 3] > xyxy[:, 1]).all()
            for v, w, _ in rec.relations:
                assert v in ids and w in ids and cls[v] == VEHICLE and cls[w] == WHEEL
            for rear, front in rec.wheel_pairs:
                assert rear in ids and front in ids


@pytest.mark.parametrize(("axis", "value", "message"), [
    ("bodies", ["sedan", "limousine"], "data.domain.bodies: unknown families ['limousine']"),
    ("skies", [], "data.domain.skies: expected a non-empty list"),
    ("props_per_frame", [5, 2], "data.domain.props_per_frame: expected min <= max"),
])
def test_a_bad_domain_config_names_the_field(domains, axis, value, message):
    train, _ = domains
    with pytest.raises(ValueError, match=re.escape(message)):
        DomainConfig.from_cfg(dict(train["domain"], **{axis: value}))


def test_the_held_out_stage_puts_every_image_in_its_test_split(domains, tmp_path):
    from deepword.word_format import open_dataset
    from stages.data.stage import run_heldout

    _, heldout = domains
    cfg = OmegaConf.create({"shift": {"data": dict(heldout, frames=4)}, "seed": 1})
    metrics = run_heldout(cfg, {}, tmp_path)
    ds = open_dataset(tmp_path)
    assert ds.records and len(ds.subset("test")) == len(ds.records)
    assert not ds.subset("train") and not ds.subset("val")
    assert metrics["data.shift.test.images"] == len(ds.records)
    assert all(k.startswith("data.shift.test.") for k in metrics)


def test_a_bad_domain_config_fails_before_the_worker_pool_starts(domains, tmp_path):
    train, _ = domains
    bad = dict(train, frames=4, domain=dict(train["domain"], grounds=["lava"]))
    with pytest.raises(ValueError, match=re.escape("data.domain.grounds: unknown families ['lava']")):
        generate(bad, 0, tmp_path, workers=2, progress=False)
