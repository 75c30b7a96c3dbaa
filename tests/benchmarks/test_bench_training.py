"""The training benchmark's parts run on the current code (a bench is run by hand, so a broken one goes unseen)."""

from benchmarks.bench_detector_training import facing_step_ratio, loader_share, relation_step_ratio
from benchmarks.bench_latency import default_configs

PEAKS = {"fp32": 1e11, "bf16": 2e11}


def test_the_loader_row_runs_on_the_datasets_cached_items(capsys):
    _, det = default_configs()
    loader_share(det, 0.01, rounds=1, items=2)
    out = capsys.readouterr().out
    assert "quick: 480x352, 320x256 crops" in out and "full: whole 640x480" in out


def test_the_relation_and_facing_steps_are_timed_in_both_layouts(capsys):
    relation_step_ratio(1, PEAKS, native_bf16=False, images=2)
    facing_step_ratio(1, PEAKS, native_bf16=False)
    out = capsys.readouterr().out
    assert out.count("fp32 channels_last") == 4  # each network's ratio row and utilisation row
    assert "relation step:" in out and "facing step:" in out
