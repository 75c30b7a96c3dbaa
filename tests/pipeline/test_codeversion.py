"""Code versions come from static import analysis: own package + transitively imported project modules."""

import json
import sys

from pipeline.codeversion import clear_memo, code_version


def test_version_covers_package_and_transitive_project_imports_without_importing(toy):
    v = code_version(f"{toy.package}.alpha.stage", frozenset({toy.package, "pipeline"}))
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
    v = code_version(f"{toy.package}_solo", frozenset({toy.package, "pipeline"}))
    assert set(v.files) == {f"{toy.package}_solo.py"}


def test_whole_stage_package_and_function_level_relative_imports_are_followed(toy):
    assert set(code_version(f"{toy.package}.gamma.stage").files) == {
        f"{toy.package}/__init__.py", f"{toy.package}/gamma/__init__.py", f"{toy.package}/gamma/stage.py"}
    toy.edit("gamma/helpers.py", "def run(cfg, inputs, out_dir):\n    from .. import unused\n    return {}\n")
    files = code_version(f"{toy.package}.gamma.stage").files
    assert f"{toy.package}/gamma/helpers.py" in files, "every file of the stage's package counts"
    assert f"{toy.package}/unused.py" in files


def test_a_change_in_a_library_package_changes_the_key_only_when_code_packages_names_it(toy):
    """A stage's code version follows the project modules it imports in the packages ``pipeline.code_packages``
    names (docs/engine.md): a library package beside the stages must be named there."""
    from pipeline.dag import load_stages
    from pipeline.keys import key_parts

    lib = f"{toy.package}_lib"
    (toy.root / lib).mkdir()
    (toy.root / lib / "__init__.py").write_text("")
    (toy.root / lib / "scaling.py").write_text("FACTOR = 2\n")
    toy.edit("gamma/stage.py", f"from {lib}.scaling import FACTOR\n\ndef run(cfg, inputs, out_dir):\n    return {{}}\n")

    def key(**dotted):
        cfg = toy.config(**dotted)
        return key_parts(load_stages(cfg)["c"], cfg, {}).key

    named = {"pipeline.code_packages": [toy.package, lib, "pipeline"]}
    before, before_unnamed = key(**named), key()
    (toy.root / lib / "scaling.py").write_text("FACTOR = 3\n")
    clear_memo()
    assert key(**named) != before, "a change in a named library package changes the stage's key"
    assert key() == before_unnamed, "a package code_packages does not name is not followed"


def test_import_lists_persist_by_content_and_an_edit_is_parsed_again(toy, monkeypatch):
    import pipeline.codeversion as cv

    memo = toy.root / "memo.json"
    module = f"{toy.package}.alpha.stage"
    with cv.persistent_imports(memo):
        first = code_version(module, frozenset({toy.package, "pipeline"}))
    assert memo.is_file()
    cv._IMPORTS_MEMO.clear()  # a new process: only the file remembers
    parsed = []
    real_parse = cv._parse_imports
    monkeypatch.setattr(cv, "_parse_imports", lambda source, path: parsed.append(path.name) or real_parse(source, path))
    with cv.persistent_imports(memo):
        again = code_version(module, frozenset({toy.package, "pipeline"}))
    assert again == first and parsed == [], "nothing parsed: every file's imports came from the memo"

    toy.edit("common.py", "import json\n\nfrom .unused import X\n\ndef scale(x):\n    return 2 * x + X - 1\n")
    cv._IMPORTS_MEMO.clear()
    with cv.persistent_imports(memo):
        edited = code_version(module, frozenset({toy.package, "pipeline"}))
    assert sorted(parsed) == ["common.py", "unused.py"], "only the edited file and the one it now imports are parsed"
    assert f"{toy.package}/unused.py" in edited.files and edited.digest != first.digest

    memo.write_text("{not json")  # a damaged memo is ignored and written again
    cv._IMPORTS_MEMO.clear()
    with cv.persistent_imports(memo):
        assert code_version(module, frozenset({toy.package, "pipeline"})) == edited
    assert json.loads(memo.read_text())["format"] == cv._DISK_FORMAT
