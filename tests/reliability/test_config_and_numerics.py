"""Config errors stop a run before any stage; a NaN loss stops training with a clear message; a poisoned
checkpoint is refused by ``weights_only=True`` loading. In-process on the tiny WORD dataset."""

from __future__ import annotations

import pathlib
import pickle
from pathlib import Path

import pytest
import torch
from hydra.errors import MissingConfigException

from pipeline.dag import load_stages
from pipeline.errors import PipelineError
from pipeline.keys import key_parts
from tests.reliability.harness import complete_entries, compose_cfg, run_in_process


def nothing_cached_for_relation(cache) -> bool:
    stage_dir = cache / "relation"
    return complete_entries(cache, "relation") == [] and not list(stage_dir.glob(".partial-*"))


@pytest.mark.parametrize("group", ["relation/backbone", "detector/backbone"])
def test_unknown_backbone_fails_at_config_composition(tmp_path, tiny, group):
    with pytest.raises(MissingConfigException, match=f"{group}.*no_such_net|no_such_net.*{group}"):
        compose_cfg(tiny, tmp_path / "cache", "sqlite:///unused.db", f"{group}=no_such_net")


@pytest.mark.parametrize("override, words", [
    ("relation.train.epochs=-1", "relation.train.epochs = -1: must be >= 1"),
    ("detector.epochs=0", "detector.epochs = 0: must be >= 1"),
    ("relation.max_objects=0", "relation.max_objects = 0: must be >= 1"),
    ("relation.loss.rank_weight=-0.5", "relation.loss.rank_weight = -0.5: must be >= 0"),
    ("eval.match_iou=1.5", "eval.match_iou = 1.5: must be <= 1"),
])
def test_bad_config_value_fails_before_any_stage_runs(tmp_path, tiny, tracking_uri, override, words):
    cache = tmp_path / "cache"
    with pytest.raises(PipelineError, match="no stage was run") as info:
        run_in_process(tiny, cache, tracking_uri, override)
    assert words in str(info.value)
    assert not cache.exists()


def test_max_objects_below_an_images_objects_fails_at_relation_start_and_caches_nothing(upstream, tiny, tracking_uri):
    cache, _ = upstream
    with pytest.raises(ValueError, match=r"labels.jsonl:\d+: image 'images/front/\d+.png' has 12 objects, more than "
                                         r"relation.max_objects=4") as info:
        run_in_process(tiny, cache, tracking_uri, "pipeline.until=relation", "relation.max_objects=4")
    assert info.value.pipeline_stage == "relation"
    assert nothing_cached_for_relation(cache)  # neither an entry nor a work dir
    assert len(complete_entries(cache, "priors")) == 1  # upstream work is kept


def test_nan_loss_stops_relation_training_with_clear_message_and_caches_nothing(upstream, tiny, tracking_uri,
                                                                              monkeypatch):
    import stages.relation.lightning as rl

    real_loss = rl.relation_loss

    def nan_loss(*args, **kwargs):
        losses = real_loss(*args, **kwargs)
        return {**losses, "loss": losses["loss"] * float("nan")}

    monkeypatch.setattr(rl, "relation_loss", nan_loss)
    cache, _ = upstream
    with pytest.raises(FloatingPointError, match=r"relation: training loss is nan .* training stopped") as info:
        run_in_process(tiny, cache, tracking_uri, "pipeline.until=relation")
    assert info.value.pipeline_stage == "relation"
    assert nothing_cached_for_relation(cache)


class _Exploit:
    """Unpickling this creates ``marker``: what a malicious checkpoint could do instead."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def test_poisoned_resume_checkpoint_is_refused_by_weights_only_loading(tmp_path, upstream, tiny, tracking_uri):
    cache, input_keys = upstream
    cfg = compose_cfg(tiny, cache, tracking_uri, "pipeline.until=relation")
    key = key_parts(load_stages(cfg)["relation"], cfg, input_keys).key
    marker = tmp_path / "code_ran"
    # the smoke profile trains an ensemble: its first member's checkpoint is the one a resume loads first
    member = Path("members", "0") if int(cfg.relation.ensemble) > 1 else Path()
    ckpt = cache / "relation" / f".partial-{key}" / "out" / member / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    torch.save({"state_dict": _Exploit(marker), "epoch": 0, "global_step": 1}, ckpt)
    probe = tmp_path / "probe.ckpt"  # the premise: loading it unsafely runs code
    torch.save({"x": _Exploit(tmp_path / "probe_ran")}, probe)
    torch.load(probe, weights_only=False)
    assert (tmp_path / "probe_ran").exists()

    with pytest.raises(pickle.UnpicklingError, match="Weights only load failed") as info:
        run_in_process(tiny, cache, tracking_uri, "pipeline.until=relation")
    assert info.value.pipeline_stage == "relation"
    assert not marker.exists()
    assert nothing_cached_for_relation(cache)  # the poisoned work dir is discarded, not resumed again
