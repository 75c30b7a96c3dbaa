"""Code versions come from static import analysis: own package + transitively imported project modules."""

import sys

from pipeline.codeversion import code_version
from pipeline.keys import PROJECT_PACKAGES


def test_version_covers_package_and_transitive_project_imports_without_importing(toy):
    v = code_version(f"{toy.package}.alpha.stage", PROJECT_PACKAGES)
    p = toy.package
    assert set(v.files) == {
        f"{p}/__init__.py", f"{p}/alpha/__init__.py", f"{p}/alpha/stage.py", f"{p}/common.py",
        "pipeline/__init__.py", "pipeline/tracking.py",
    }
    assert not any(m.startswith(p) for m in sys.modules), "finding the code version must not import it"


def test_version_changes_with_a_transitively_imported_module_only(toy):
    before = code_version(f"{toy.package}.alpha.stage").digest
    toy.edit("unused.py", "X = 2\n")
    assert code_version(f"{toy.package}.alpha.stage").digest == before, "an unimported module is not part of it"
    toy.edit("common.py", "def scale(x):\n    return 3 * x\n")
    assert code_version(f"{toy.package}.alpha.stage").digest != before


def test_top_level_module_stage_is_hashed_alone(toy):
    (toy.root / f"{toy.package}_solo.py").write_text("import json\n\ndef run(cfg, inputs, out_dir):\n    return {}\n")
    v = code_version(f"{toy.package}_solo", PROJECT_PACKAGES)
    assert set(v.files) == {f"{toy.package}_solo.py"}


def test_whole_stage_package_and_function_level_relative_imports_are_followed(toy):
    assert set(code_version(f"{toy.package}.gamma.stage").files) == {
        f"{toy.package}/__init__.py", f"{toy.package}/gamma/__init__.py", f"{toy.package}/gamma/stage.py"}
    toy.edit("gamma/helpers.py", "def run(cfg, inputs, out_dir):\n    from .. import unused\n    return {}\n")
    files = code_version(f"{toy.package}.gamma.stage").files
    assert f"{toy.package}/gamma/helpers.py" in files, "every file of the stage's package counts"
    assert f"{toy.package}/unused.py" in files
