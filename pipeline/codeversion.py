"""A stage's code version, found by static analysis: no stage code, torch or Lightning is imported.

The version covers every ``.py`` file of the package holding the stage's ``run`` module plus every
project module those files import, transitively (``import x.y``, ``from x import y``, relative imports,
including imports inside functions). "Project" means the top-level packages named in
``project_packages`` (the run module's own top-level package is always one of them); third-party
imports are ignored. Imports built from strings at run time (``importlib.import_module(name)``) are
invisible to this analysis.

Modules are located with ``importlib``'s path finders, which look at the file system only: finding a
module never executes it. A file's import list is memoised by its content hash for the process. Parsing is most
of the cost of a plan (about 150 files for the DeepWORD stages), so the import lists are also kept on disk between
runs (``persistent_imports``, which the engine holds while it plans): a file is parsed again only when its content
is new. The content is read and hashed on every plan, once per file within it.
"""

from __future__ import annotations

import ast
import contextlib
import hashlib
import importlib.machinery
import importlib.util
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from pipeline.cache import replace_text_best_effort
from pipeline.errors import PipelineError


@dataclass(frozen=True)
class CodeVersion:
    """``digest`` goes into the cache key; ``files`` (display path -> sha256) explains a change."""

    digest: str
    files: dict[str, str]


Imports = list[tuple[str, int, tuple[str, ...]]]  # (module, level, imported names) of each import statement

_IMPORTS_MEMO: dict[str, Imports] = {}  # content sha256 -> imports
_SPEC_MEMO: dict[str, tuple[Path | None, bool]] = {}
# While ``persistent_imports`` is active: each file's hash, read once in the block (path -> sha256), and the
# on-disk memo (content sha256 -> imports) with the hashes this block used.
_plan_hashes: dict[Path, str] | None = None
_DISK_FORMAT = 1
_disk: dict[str, Imports] | None = None
_disk_used: set[str] = set()
_disk_added = False
DISK_MEMO_ENTRIES = 4096  # beyond this, a save keeps only the entries this run used


def _locate(module: str) -> tuple[Path | None, bool]:
    """(source file, is_package) of ``module`` without importing anything; (None, False) if not found."""
    if module in _SPEC_MEMO:
        return _SPEC_MEMO[module]
    parent, _, _ = module.rpartition(".")
    if parent:
        parent_file, parent_is_pkg = _locate(parent)
        if parent_file is None or not parent_is_pkg:
            result: tuple[Path | None, bool] = (None, False)
            _SPEC_MEMO[module] = result
            return result
        spec = importlib.machinery.PathFinder.find_spec(module, [str(parent_file.parent)])
    else:
        # Top-level names: find_spec consults sys.path and meta-path finders (editable installs)
        # but imports nothing for a name without dots.
        try:
            spec = importlib.util.find_spec(module)
        except (ImportError, ValueError):
            spec = None
    result = (None, False)
    if spec is not None and spec.origin and spec.origin.endswith(".py"):
        result = (Path(spec.origin).resolve(), spec.submodule_search_locations is not None)
    elif spec is not None and spec.submodule_search_locations:  # namespace package: no __init__.py
        first = next(iter(spec.submodule_search_locations))
        result = (Path(first).resolve() / "__init__.py", True)
    _SPEC_MEMO[module] = result
    return result


def _module_name(path: Path, root_pkg: str, root_dir: Path) -> str:
    rel = path.relative_to(root_dir).with_suffix("")
    parts = [root_pkg, *rel.parts]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _parse_imports(source: bytes, path: Path) -> Imports:
    try:
        tree = ast.parse(source, filename=str(path))
    except SyntaxError as exc:
        raise PipelineError(f"cannot compute the code version: syntax error in {path}:{exc.lineno}: {exc.msg}") from exc
    found: Imports = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((alias.name, 0, ()) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.append((node.module or "", node.level, tuple(a.name for a in node.names)))
    return found


def _read_file(path: Path) -> tuple[str, Imports]:
    """(sha256 of the content, its import statements)."""
    global _disk_added
    digest = _plan_hashes.get(path) if _plan_hashes is not None else None
    source = None
    if digest is None:
        source = path.read_bytes()
        digest = hashlib.sha256(source).hexdigest()
        if _plan_hashes is not None:
            _plan_hashes[path] = digest
    found = _IMPORTS_MEMO.get(digest)
    if found is None and _disk is not None:
        found = _disk.get(digest)
    if found is None:
        found = _parse_imports(path.read_bytes() if source is None else source, path)
    _IMPORTS_MEMO[digest] = found
    if _disk is not None:
        if digest not in _disk:
            _disk[digest] = found
            _disk_added = True
        _disk_used.add(digest)
    return digest, found


def _raw_imports(path: Path) -> Imports:
    """(module, level, imported names) of every import statement in ``path``."""
    return _read_file(path)[1]


def _load_disk_memo(path: Path) -> dict[str, Imports]:
    try:
        data = json.loads(path.read_text())
        if data.get("format") != _DISK_FORMAT or data.get("python") != list(sys.version_info[:2]):
            return {}
        return {str(digest): [(str(m), int(level), tuple(str(n) for n in names)) for m, level, names in imports]
                for digest, imports in data["imports"].items()}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return {}  # absent or unreadable: every file is parsed, and the memo written again


def _save_disk_memo(path: Path, memo: dict[str, Imports]) -> None:
    if len(memo) > DISK_MEMO_ENTRIES:
        memo = {d: v for d, v in memo.items() if d in _disk_used}
    data = {"format": _DISK_FORMAT, "python": list(sys.version_info[:2]),
            "imports": {d: [[m, level, list(names)] for m, level, names in v] for d, v in memo.items()}}
    # a read-only cache: the next run parses again, nothing else changes
    replace_text_best_effort(path, json.dumps(data, separators=(",", ":")))


@contextlib.contextmanager
def persistent_imports(path: Path):
    """Within the block, import lists come from and go to the JSON file ``path`` (keyed by content hash), and each
    file is read and hashed once: a plan."""
    global _disk, _disk_added, _plan_hashes
    _disk, _disk_added, _plan_hashes = _load_disk_memo(path), False, {}
    _disk_used.clear()
    try:
        yield
        if _disk_added or len(_disk) > DISK_MEMO_ENTRIES:
            _save_disk_memo(path, _disk)
    finally:
        _disk, _disk_added, _plan_hashes = None, False, None
        _disk_used.clear()


def _imported_modules(path: Path, module: str, is_package: bool) -> set[str]:
    """Absolute names of every module an import statement in ``path`` may execute."""
    names: set[str] = set()
    package = module if is_package else module.rpartition(".")[0]
    for target, level, members in _raw_imports(path):
        if level:
            base_parts = package.split(".") if package else []
            if level - 1 > len(base_parts):
                continue  # beyond the top-level package: Python would fail too
            base = ".".join(base_parts[: len(base_parts) - (level - 1)])
            target = f"{base}.{target}" if target and base else (target or base)
        if not target:
            continue
        parts = target.split(".")
        names.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))  # parents' __init__ run too
        names.update(f"{target}.{m}" for m in members if m != "*")  # `from pkg import submodule`
    return names


def _package_files(run_module: str) -> tuple[list[tuple[str, Path]], str]:
    """(module name, file) of every .py in the run module's package (or the module alone if top-level)."""
    run_file, run_is_pkg = _locate(run_module)
    if run_file is None:
        raise PipelineError(f"cannot find the source of module '{run_module}' (is it on sys.path?)")
    package = run_module if run_is_pkg else run_module.rpartition(".")[0]
    if not package:
        return [(run_module, run_file)], run_module
    pkg_dir = run_file.parent
    files = sorted(p for p in pkg_dir.rglob("*.py") if "__pycache__" not in p.parts)
    return [(_module_name(p, package, pkg_dir), p) for p in files], package


def _display_path(path: Path, top_module: str) -> str:
    """The path below the directory holding the top-level package, e.g. ``stages/data/stage.py``."""
    top_file, top_is_pkg = _locate(top_module)
    if top_file is None:
        return path.name
    root = top_file.parent.parent if top_is_pkg else top_file.parent
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.name


def code_version(run_module: str, project_packages: frozenset[str] = frozenset()) -> CodeVersion:
    """Hash the run module's package plus every project module it imports, transitively."""
    start, package = _package_files(run_module)
    projects = set(project_packages) | {package.split(".")[0]}
    seen: dict[Path, str] = {}
    todo: list[tuple[str, Path, bool]] = [(m, p, p.name == "__init__.py") for m, p in start]
    # The parents of the stage's package execute when it is imported.
    parents = package.split(".")
    for i in range(1, len(parents)):
        parent_file, _ = _locate(".".join(parents[:i]))
        if parent_file is not None:
            todo.append((".".join(parents[:i]), parent_file, True))
    while todo:
        module, path, is_pkg = todo.pop()
        if path in seen or not path.is_file():
            continue
        seen[path] = module
        for name in _imported_modules(path, module, is_pkg):
            if name.split(".")[0] not in projects:
                continue
            found, found_is_pkg = _locate(name)
            if found is not None and found not in seen:
                todo.append((name, found, found_is_pkg))
    files: dict[str, str] = {}
    for path, module in seen.items():
        files[_display_path(path, module.split(".")[0])] = _read_file(path)[0]
    digest = hashlib.sha256("\n".join(f"{k} {v}" for k, v in sorted(files.items())).encode()).hexdigest()
    return CodeVersion(digest=digest, files=dict(sorted(files.items())))


def clear_memo() -> None:
    """Forget located modules (tests create packages on the fly)."""
    _SPEC_MEMO.clear()
    importlib.invalidate_caches()
