"""What a stage hands downstream: its declared ``outputs`` and the ``inputs`` mapping a stage receives.

A stage may declare, in its ``pipeline.stages.<name>`` entry, the files other stages read from its output
directory, as ``outputs: {name: relative path}``. A path may hold ``{field}`` placeholders: a family of files
(``predictions: predictions/{boxes}_{method}.jsonl``) whose reader fills the fields in. The engine checks the
declarations before any stage runs (relative, inside the directory), checks after a stage runs (and on a cache
hit) that each declared output exists (a pattern: at least one file matches it), and hands them downstream.

A stage's ``inputs`` is a ``StageInputs``: a dict {input stage: its output directory}, as before, plus
``inputs.output(stage, name, **fields)``, the path of that input's declared output. Reading a stage that is not
a declared input is an error that names the stage and its declared inputs, as is asking for an undeclared output:
a stage reads another stage's files by the names that stage declares, never by importing its code.
"""

from __future__ import annotations

import string
from collections.abc import Iterable, Mapping
from pathlib import Path, PurePosixPath

from pipeline.errors import PipelineError


class UndeclaredInput(PipelineError, KeyError):
    """A stage read an input it does not declare, or an output its input does not declare."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def pattern_fields(pattern: str) -> list[str]:
    return [name for _, name, _, _ in string.Formatter().parse(pattern) if name is not None]


def check_declared(stage: str, outputs: Mapping[str, str]) -> None:
    """Each output is a relative path inside the stage's directory, with at most plain ``{field}`` placeholders."""
    for name, pattern in outputs.items():
        where = f"pipeline.stages.{stage}.outputs.{name}"
        path = PurePosixPath(pattern)
        if not pattern or path.is_absolute() or ".." in path.parts:
            raise PipelineError(f"{where}: expected a relative path inside the stage's directory, got {pattern!r}")
        try:
            fields = pattern_fields(pattern)
        except ValueError as exc:
            raise PipelineError(f"{where}: {pattern!r} is not a path pattern: {exc}") from None
        bad = [f for f in fields if not f.isidentifier()]
        if bad:
            raise PipelineError(f"{where}: placeholders must be plain names like {{method}}, got {bad}")


def missing_outputs(out_dir: Path, outputs: Mapping[str, str]) -> list[str]:
    """The declared outputs absent from ``out_dir`` (a pattern: no file matches it)."""
    missing = []
    for name, pattern in outputs.items():
        fields = pattern_fields(pattern)
        if fields:
            found = any(p.is_file() for p in out_dir.glob(pattern.format(**{f: "*" for f in fields})))
        else:
            found = (out_dir / pattern).is_file()
        if not found:
            missing.append(f"{name} ({pattern})")
    return missing


class StageInputs(dict):
    """{input stage: its output directory} for one stage, with its inputs' declared outputs."""

    def __init__(self, stage: str, dirs: Mapping[str, Path], declared: Iterable[str],
                 outputs: Mapping[str, Mapping[str, str]]):
        super().__init__(dirs)
        self.stage, self.declared = stage, tuple(declared)
        self.declared_outputs = {name: dict(outputs.get(name) or {}) for name in self.declared}

    def __missing__(self, name: str):
        if name in self.declared:
            raise UndeclaredInput(f"stage '{self.stage}': its optional input '{name}' is not part of this run "
                                  f"(test `'{name}' in inputs` first)")
        raise UndeclaredInput(f"stage '{self.stage}' reads '{name}', which is not among its declared inputs "
                              f"{list(self.declared)} (pipeline.stages.{self.stage}.inputs)")

    def output(self, stage: str, name: str, **fields) -> Path:
        """The path of ``stage``'s declared output ``name``, its ``{field}`` placeholders filled from ``fields``."""
        directory = Path(self[stage])
        declared = self.declared_outputs[stage]
        if name not in declared:
            raise UndeclaredInput(f"stage '{self.stage}' reads output '{name}' of '{stage}', which declares "
                                  f"{sorted(declared) or 'no outputs'} (pipeline.stages.{stage}.outputs)")
        pattern = declared[name]
        try:
            return directory / pattern.format(**fields)
        except KeyError as exc:
            raise UndeclaredInput(f"stage '{self.stage}': output '{name}' of '{stage}' ({pattern}) needs "
                                  f"{pattern_fields(pattern)}; missing {exc.args[0]!r}") from None
