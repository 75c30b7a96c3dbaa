"""Stages declare the files downstream stages read (``outputs``); the engine checks them and hands them on."""

import pytest

from pipeline.errors import PipelineError
from pipeline.outputs import StageInputs, UndeclaredInput
from pipeline.runner import run_pipeline

READS_DECLARED = """
def run(cfg, inputs, out_dir):
    value = int(inputs.output("a", "value").read_text())
    one = inputs.output("a", "parts", part="one").read_text()
    (out_dir / "sum.txt").write_text(str(value + cfg.beta.offset) + one)
    return {"beta.sum": float(value + cfg.beta.offset)}
"""

WRITES_PARTS = """
from pathlib import Path

def run(cfg, inputs, out_dir):
    (out_dir / "value.txt").write_text(str(2 * cfg.alpha.value))
    (out_dir / "parts").mkdir()
    (out_dir / "parts" / "one.txt").write_text("1")
    return {}
"""

READS_UNDECLARED = """
def run(cfg, inputs, out_dir):
    return {"n": float(len(list(inputs["a"].iterdir())))}
"""


def declared(toy, **dotted):
    return toy.config(**{"pipeline.stages.a.outputs": {"value": "value.txt", "parts": "parts/{part}.txt"},
                         **dotted})


def run(toy, cfg):
    return run_pipeline(cfg, run_dir=toy.root / "run", in_process_tracking=True)


def test_a_stage_reads_its_inputs_declared_outputs_by_name(toy):
    toy.edit("alpha/stage.py", WRITES_PARTS)
    toy.edit("beta/stage.py", READS_DECLARED)
    summary = run(toy, declared(toy))
    assert summary["stages"]["b"]["metrics"] == {"beta.sum": 16.0}


def test_a_declared_output_the_stage_did_not_write_fails_the_stage_and_leaves_no_entry(toy):
    cfg = declared(toy)  # the toy's alpha writes value.txt but no parts/*.txt
    with pytest.raises(PipelineError, match=r"stage 'a' did not write its declared output\(s\) \['parts \(parts/\{part\}.txt\)'\]"):
        run(toy, cfg)
    assert not list((toy.root / "cache" / "a").glob("*/manifest.json"))


def test_outputs_must_be_relative_paths_inside_the_stage_directory(toy):
    for bad in ("/etc/passwd", "../x.txt", "a/{}.txt"):
        with pytest.raises(PipelineError, match="pipeline.stages.a.outputs.value"):
            run(toy, toy.config(**{"pipeline.stages.a.outputs": {"value": bad}}))


def test_reading_an_undeclared_input_or_output_is_an_error_naming_both():
    inputs = StageInputs("b", {"a": "/x"}, ["a", "o"], {"a": {"value": "v.txt"}})
    with pytest.raises(UndeclaredInput, match=r"stage 'b' reads 'c', which is not among its declared inputs \['a', 'o'\]"):
        inputs["c"]
    with pytest.raises(UndeclaredInput, match="optional input 'o' is not part of this run"):
        inputs["o"]
    with pytest.raises(UndeclaredInput, match=r"reads output 'other' of 'a', which declares \['value'\]"):
        inputs.output("a", "other")
    assert str(inputs.output("a", "value")) == "/x/v.txt" and "c" not in inputs


def test_an_undeclared_input_fails_the_stage_that_reads_it(toy):
    toy.edit("gamma/stage.py", READS_UNDECLARED)
    with pytest.raises(PipelineError, match="stage 'c' reads 'a', which is not among its declared inputs"):
        run(toy, toy.config())
