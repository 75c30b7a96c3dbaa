"""The new domain's labelled pool (stages/data/pool.py) and the dataset composed of several sources
(stages/data/compose.py, data=adapt): which images a run takes, how they split, and what the data stage writes."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from deepword.word_format import PRIOR_SPLIT, SPLITS, DatasetError, open_dataset
from stages.data.compose import build_sources, train_repeats
from stages.data.pool import PoolTooSmall, draw_order, pool_splits, take_images, val_positions
from stages.data.stage import build_dataset
from tests.stages.data.data_helpers import CONF, synword_cfg

SEED = 7


def pool_cfg(images: int, draw: int = 0, frames: int = 40) -> dict:
    """data=adapt's pool source on the held-out families at smoke size (what the profile makes of shift.data)."""
    shift = OmegaConf.load(CONF.parent / "shift" / "heldout.yaml")["data"]
    generator = OmegaConf.to_container(OmegaConf.merge(OmegaConf.create(synword_cfg(frames=4)), shift), resolve=True)
    generator.update(image_size=[160, 120], workers=1)   # a quarter of the smoke size: what is checked is which images
    src = OmegaConf.to_container(OmegaConf.load(CONF / "adapt.yaml")["sources"]["pool"], resolve=False)
    src.update(generator=generator, images=images, draw=draw, frames=frames)
    return src


def take(tmp_path, name: str, **kw):
    out = tmp_path / name
    out.mkdir()
    recs, frames = take_images(pool_cfg(**kw), SEED, out, progress=False)
    return out, recs, frames


def test_a_draw_is_a_fixed_order_of_the_pools_frames_and_draws_differ():
    a = draw_order(40, 100000, SEED, 0)
    assert a == draw_order(40, 100000, SEED, 0) and sorted(a) == list(range(100000, 100040))
    assert a != draw_order(40, 100000, SEED, 1) and a != draw_order(40, 100000, SEED + 1, 0)


def test_val_is_the_first_frame_then_one_in_five_and_a_longer_take_extends_the_split():
    assert val_positions(7, 0.2) == {0, 5}
    assert val_positions(31, 0.2) == {0, 5, 10, 15, 20, 25, 30}   # exact fractions: no drift at 15 (0.2 x 15)
    assert val_positions(1, 0.2) == {0}                             # never an empty val split
    assert val_positions(7, 0.2) <= val_positions(14, 0.2)
    with pytest.raises(ValueError, match="val_share"):
        val_positions(4, 1.0)


def test_the_take_is_deterministic_nested_and_other_draws_take_other_images(tmp_path):
    d25, r25, f25 = take(tmp_path, "n25", images=25)
    _, again, _ = take(tmp_path, "n25_again", images=25)
    d12, r12, f12 = take(tmp_path, "n12", images=12)
    _, other, _ = take(tmp_path, "draw1", images=25, draw=1)
    assert len(r25) == 25 and len(r12) == 12 and len(other) == 25
    assert [r.to_json() for r in again] == [r.to_json() for r in r25]
    assert [r.image for r in r25[:12]] == [r.image for r in r12]          # N=12 is the start of N=25
    assert f25[:len(f12)] == f12
    assert {r.frame_id for r in other} != {r.frame_id for r in r25}       # another draw, other frames
    assert all(r.frame_id >= 100000 and r.relations for r in r25)          # pool frames; only labelled images
    assert all(r.extra["domain"]["ground"] in ("brick", "grass") for r in r25)   # the held-out families
    # only the taken images are left on disk
    assert sorted(p.relative_to(d25).as_posix() for p in d25.glob("images/*/*.png")) == sorted(r.image for r in r25)
    s25, s12 = pool_splits(r25, f25, 0.2), pool_splits(r12, f12, 0.2)
    assert not s25["test"] and s25["val"] and s25["train"]
    assert set(s12["train"]) <= set(s25["train"]) and set(s12["val"]) <= set(s25["val"])
    val_frames = {r.frame_id for r in r25 if r.image in s25["val"]}
    assert not val_frames & {r.frame_id for r in r25 if r.image in s25["train"]}   # split by frame


def test_n_larger_than_the_pool_is_a_clear_error(tmp_path):
    with pytest.raises(PoolTooSmall, match=r"images=100 asks for more images than the pool's 3 frames x 4 cameras"):
        take(tmp_path, "big", images=100, frames=3)
    # within 4 x frames, but more than the frames' labelled images: some cameras see no owner-member relation
    with pytest.raises(PoolTooSmall, match=r"images=12, but the pool's 3 frames hold only \d+ images with an owner-member "
                                           r"relation \(draw 0\); raise data.sources.pool.frames"):
        take(tmp_path, "all", images=12, frames=3)

def adapt_cfg(recipe_use: dict, share=None, synword_frames: int = 4) -> dict:
    syn = synword_cfg(frames=synword_frames)
    syn.update(use=recipe_use, train_share=None, max_repeat=None)
    pool = pool_cfg(images=10)
    pool.update(train_share=share, max_repeat=16)
    return {"name": "adapt", "max_easy_vehicles": 3, "sources": {"synword": syn, "pool": pool}}


def test_the_composed_data_stage_writes_a_valid_dataset_of_both_sources(tmp_path):
    cfg = adapt_cfg({"train": "train", "val": None, "test": "test", "val_prior": "val"})   # the mixed recipe's
    metrics = build_dataset(cfg, SEED, tmp_path)
    ds = open_dataset(tmp_path)                                          # every record validated on read
    source = {r.image: r.extra["data_source"] for r in ds.records}
    assert set(source.values()) == {"synword", "pool"}
    assert {source[i] for i in ds.splits["train"]} == {"synword", "pool"}
    assert {source[i] for i in ds.splits["val"]} == {"pool"}             # every recipe chooses on the pool's val
    assert {source[i] for i in ds.splits["test"]} == {"synword"}         # the generator's test split
    assert set(ds.splits["easy"]) | set(ds.splits["hard"]) == set(ds.splits["test"])
    # the generator's own splits, exactly as data=synword makes them with the same seed
    alone = tmp_path.parent / "alone"
    alone.mkdir()
    build_dataset(synword_cfg(frames=4), SEED, alone)
    own = open_dataset(alone).splits
    assert ds.splits["test"] == own["test"] and [i for i in ds.splits["train"] if source[i] == "synword"] == own["train"]
    # the generator's val split steadies the operating point (val_prior), and nothing else takes it
    assert ds.splits[PRIOR_SPLIT] == own["val"] and not set(own["val"]) & set(ds.splits["val"] + ds.splits["train"])
    assert PRIOR_SPLIT not in own                                        # a dataset without one writes none
    assert metrics["data.pool.images"] == 10.0 and metrics["data.test.images"] == len(own["test"])
    assert (tmp_path / "artifacts" / "contact_sheet_pool.png").is_file()
    assert (tmp_path / "artifacts" / "contact_sheet_synword.png").is_file()


def test_repeats_give_the_new_images_about_their_share_of_the_train_split():
    sources = {"synword": {"train_share": None}, "pool": {"train_share": 0.25, "max_repeat": 16}}

    def parts(n_syn, n_pool):
        return {"synword": {"train": ["s"] * n_syn}, "pool": {"train": ["p"] * n_pool}}

    assert train_repeats(sources, parts(840, 20)) == {"synword": 1, "pool": 14}   # 280 / 1,120 = 25 %
    assert train_repeats(sources, parts(840, 320)) == {"synword": 1, "pool": 1}   # already more than a quarter
    assert train_repeats(sources, parts(840, 4))["pool"] == 16                    # capped
    assert train_repeats(sources, parts(0, 20))["pool"] == 1                      # nothing to weigh against


def test_composition_errors_name_the_source(tmp_path):
    cfg = adapt_cfg({"train": None, "val": None, "test": "test"})
    cfg["sources"]["twin"] = dict(cfg["sources"]["synword"])               # the same frames twice
    with pytest.raises(DatasetError, match=r"data.sources.twin.*also source 'synword'"):
        build_sources(cfg, SEED, tmp_path / "twin")
    cfg = adapt_cfg({"train": None, "val": None, "test": None})
    with pytest.raises(DatasetError, match="no source gives the test split an image"):
        build_sources(cfg, SEED, tmp_path / "no_test")
    cfg = adapt_cfg({"train": None, "val": None, "test": "tset"})
    with pytest.raises(ValueError, match=r"data.sources.synword.use.test: 'tset' is not a split"):
        build_sources(cfg, SEED, tmp_path / "typo")
    cfg = adapt_cfg({"train": None, "val": None, "test": "test", "prior": "val"})
    with pytest.raises(ValueError, match=r"data.sources.synword.use: unknown split 'prior' \(have train, val, test, "
                                         r"val_prior\)"):
        build_sources(cfg, SEED, tmp_path / "prior")
    cfg["sources"]["synword"].update(name="coco", use={"test": "test"})
    with pytest.raises(ValueError, match="data.sources.synword.name: 'coco' cannot be composed"):
        build_sources(cfg, SEED, tmp_path / "coco")
    assert set(SPLITS) == {"train", "val", "test"}


def yours_cfg(root) -> dict:
    """data=mixed's source of your own images (a WORD directory), as conf/data/mixed.yaml gives it."""
    src = OmegaConf.to_container(OmegaConf.load(CONF / "mixed.yaml")["sources"]["yours"], resolve=False)
    src.update(root=str(root), max_easy_vehicles=3)
    return src


def test_a_word_directory_composes_beside_the_generator(tmp_path):
    camera = tmp_path / "my_camera"          # a WORD directory: another seed's renders stand in for your images
    camera.mkdir()
    build_dataset(synword_cfg(frames=4), SEED + 1, camera)
    theirs = open_dataset(camera).records
    syn = synword_cfg(frames=4)
    syn.update(use={"train": "train", "val": None, "test": None}, train_share=None, max_repeat=None)
    cfg = {"name": "mixed", "max_easy_vehicles": 3, "sources": {"synword": syn, "yours": yours_cfg(camera)}}
    out = tmp_path / "out"
    out.mkdir()
    metrics = build_dataset(cfg, SEED, out)
    ds = open_dataset(out)                                               # every record validated on read
    source = {r.image: r.extra["data_source"] for r in ds.records}
    assert {source[i] for i in ds.splits["train"]} == {"synword", "yours"}
    assert {source[i] for i in ds.splits["val"]} == {"yours"} and {source[i] for i in ds.splits["test"]} == {"yours"}
    mine = {r.image: r for r in ds.records if source[r.image] == "yours"}
    assert sorted(mine) == sorted(f"yours/{r.image}" for r in theirs) and metrics["data.yours.images"] == len(theirs)
    for rec in theirs:                                                   # the images linked in, frames moved clear
        linked = mine[f"yours/{rec.image}"]
        assert (out / linked.image).read_bytes() == (camera / rec.image).read_bytes()
        assert linked.frame_id == rec.frame_id + 1_000_000 and linked.relations == rec.relations
    assert (out / "artifacts" / "contact_sheet_yours.png").is_file()

    same_frames = dict(cfg, sources={"synword": syn, "yours": dict(yours_cfg(camera), first_frame=0)})
    with pytest.raises(DatasetError, match=r"data.sources.yours.*also source 'synword'.*another first_frame"):
        build_sources(same_frames, SEED, tmp_path / "same_frames")
    with pytest.raises(ValueError, match=r"data.sources.yours.root: the WORD directory"):
        build_sources(dict(cfg, sources={"synword": syn, "yours": dict(yours_cfg(camera), root="???")}), SEED,
                      tmp_path / "no_root")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="labels.jsonl"):
        build_sources(dict(cfg, sources={"synword": syn, "yours": yours_cfg(tmp_path / "empty")}), SEED,
                      tmp_path / "no_labels")
