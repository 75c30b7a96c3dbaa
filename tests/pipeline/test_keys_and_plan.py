"""The cache key changes exactly when one of its parts changes, and the plan says which part did."""

import os

from pipeline.runner import run_pipeline


def run(toy, cfg, capsys=None):
    summary = run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)
    out = capsys.readouterr().out if capsys else ""
    return summary, out


def keys(summary):
    return {name: s["key"] for name, s in summary["stages"].items()}


def hits(summary):
    return {name: s["hit"] for name, s in summary["stages"].items()}


def test_rerun_is_all_hits_and_says_up_to_date(toy, capsys):
    first, out = run(toy, toy.config(), capsys)
    assert hits(first) == {"a": False, "b": False, "c": False}
    assert out.count("MISS") == 3 and "Running stage 'a' (no entry yet)" in out
    second, out = run(toy, toy.config(), capsys)
    assert keys(second) == keys(first) and all(hits(second).values())
    assert "Stage 'a' didn't change, skipping" in out
    assert out.rstrip().endswith("Pipeline up to date.")


def test_declared_config_changes_key_and_downstream_unrelated_config_does_not(toy, capsys):
    base, _ = run(toy, toy.config(), capsys)
    same, _ = run(toy, toy.config(**{"unrelated.knob": 2, "gamma.x": 1}), capsys)
    assert keys(same) == keys(base), "unrelated config must not change any key"
    changed, out = run(toy, toy.config(**{"alpha.value": 4}), capsys)
    assert changed["stages"]["a"]["key"] != base["stages"]["a"]["key"]
    assert changed["stages"]["b"]["key"] != base["stages"]["b"]["key"], "an input key change propagates"
    assert changed["stages"]["c"]["key"] == base["stages"]["c"]["key"]
    assert hits(changed) == {"a": False, "b": False, "c": True}
    assert "config changed: alpha.value: 3 -> 4" in out
    assert "input a changed" in out
    assert changed["stages"]["b"]["metrics"] == {"beta.sum": 18.0}


def test_code_change_in_imported_module_invalidates_and_is_named(toy, capsys):
    base, _ = run(toy, toy.config(), capsys)
    toy.edit("common.py", "def scale(x):\n    return 2 * x  # same behaviour, new source\n")
    changed, out = run(toy, toy.config(), capsys)
    assert hits(changed) == {"a": False, "b": False, "c": True}
    assert f"code changed: {toy.package}/common.py" in out
    assert changed["stages"]["c"]["key"] == base["stages"]["c"]["key"]


def test_watched_file_and_directory_changes_invalidate(toy, capsys):
    base, _ = run(toy, toy.config(), capsys)
    labels = toy.root / "dataset" / "labels.jsonl"
    labels.write_text('{"image": "b.png"}\n')
    changed, out = run(toy, toy.config(), capsys)
    assert hits(changed)["a"] is False and "watched files changed" in out
    # a directory contributes sizes and mtimes: touching an image invalidates, its content is not read
    image = toy.root / "dataset" / "a.png"
    image.write_bytes(b"\x89PNG")
    after_add, _ = run(toy, toy.config(), capsys)
    assert hits(after_add)["a"] is False
    os.utime(image, ns=(1, 1))
    after_touch, _ = run(toy, toy.config(), capsys)
    assert hits(after_touch)["a"] is False
    again, _ = run(toy, toy.config(), capsys)
    assert all(hits(again).values())
    assert base["stages"]["c"]["key"] == again["stages"]["c"]["key"]


def test_switching_config_back_hits_the_older_entry(toy, capsys):
    run(toy, toy.config(), capsys)
    run(toy, toy.config(**{"alpha.value": 5}), capsys)
    back, out = run(toy, toy.config(), capsys)
    assert all(hits(back).values())
    assert "cached entry from an earlier run" in out


def test_force_recomputes_only_the_named_stage(toy, capsys):
    counter = str(toy.root / "count.txt")
    run(toy, toy.config(**{"alpha.counter": counter}), capsys)
    forced, out = run(toy, toy.config(**{"alpha.counter": counter, "pipeline.force": ["a"]}), capsys)
    assert hits(forced) == {"a": False, "b": True, "c": True}
    assert "forced" in out
    assert open(counter).read().count("computed") == 2


def test_until_runs_only_the_stage_and_its_ancestors(toy, capsys):
    summary, out = run(toy, toy.config(**{"pipeline.until": "b"}), capsys)
    assert list(summary["stages"]) == ["a", "b"]
    assert summary["not_run"] == {"c": "not needed for pipeline.until"}
    assert "not run, not needed for pipeline.until: c" in out


def test_a_stage_run_without_its_optional_input_has_its_own_key_and_the_plan_says_why(toy, capsys):
    optional_a = {"pipeline.stages.c.inputs": ["a"], "pipeline.stages.c.optional": ["a"]}
    full, _ = run(toy, toy.config(**optional_a), capsys)
    assert full["stages"]["c"]["metrics"]["gamma.inputs"] == 1.0
    without, out = run(toy, toy.config(**optional_a, **{"pipeline.skip": ["a"]}), capsys)
    assert list(without["stages"]) == ["c"] and without["not_run"] == {"a": "pipeline.skip", "b": "needs a"}
    assert "not run, pipeline.skip: a" in out and "not run, needs a: b" in out
    assert "not run: pipeline.skip" in out.splitlines()[-3]  # the summary table too
    assert without["stages"]["c"]["metrics"]["gamma.inputs"] == 0.0  # the stage got no 'a' input
    assert without["stages"]["c"]["key"] != full["stages"]["c"]["key"]
    assert "inputs changed: ['a'] -> []" in out
    again, _ = run(toy, toy.config(**optional_a), capsys)
    assert all(hits(again).values())  # both variants stay cached side by side


def test_a_plan_line_names_a_few_config_changes_and_counts_the_rest():
    from pipeline.keys import KeyParts
    from pipeline.plan import CHANGES_SHOWN, explain_miss

    old = {f"k{i:02d}": i for i in range(CHANGES_SHOWN + 4)}
    new = {k: v + 1 for k, v in old.items()}
    parts = KeyParts(stage="s", code={}, code_digest="c", config=new, inputs={}, watch={})
    reason = explain_miss(parts, {"key": "old", "code_digest": "c", "config": old, "inputs": {}, "watch": {}}, None)
    assert reason.count(" -> ") == CHANGES_SHOWN
    assert reason.endswith("... and 4 more")
    assert "k00: 0 -> 1" in reason
