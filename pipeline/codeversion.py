"""A stage's code version, found by static analysis: no stage code, torch or Lightning is imported.

The version covers every ``.py`` file of the package holding the stage's ``run`` module plus every
project module those files import, transitively (``import x.y``, ``from x import y``, relative imports,
including imports inside functions). "Project" means the top-level packages named in
``project_packages`` (the run module's own top-level package is always one of them); third-party
imports are ignored. Imports built from strings at run time (``importlib.import_module(name)``) are
invisible to this analysis.

Modules are located with ``importlib``'s path finders, which look at the file system only: finding a
module never executes it. Parsed import lists are memoised per (path, size, mtime) for the process.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.machinery
import importlib.util
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import PipelineError


@dataclass(frozen=True)
class CodeVersion:
    """``digest`` goes into the cache key; ``files`` (display path -> sha256) explains a change."""

    digest: str
    files: dict[str, str]


_IMPORTS_MEMO: dict[tuple[str, int, int], list[tuple[str, int, tuple[str, ...]]]] = {}
_SPEC_MEMO: dict[str, tuple[Path | None, bool]] = {}


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


def _raw_imports(path: Path) -> list[tuple[str, int, tuple[str, ...]]]:
    """(module, level, imported names) of every import statement in ``path``."""
    st = path.stat()
    memo_key = (str(path), st.st_size, st.st_mtime_ns)
    if memo_key in _IMPORTS_MEMO:
        return _IMPORTS_MEMO[memo_key]
    try:
        tree = ast.parse(path.read_bytes(), filename=str(path))
    except SyntaxError as exc:
        raise PipelineError(f"cannot compute the code version: syntax error in {path}:{exc.lineno}: {exc.msg}") from exc
    found: list[tuple[str, int, tuple[str, ...]]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((alias.name, 0, ()) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.append((node.module or "", node.level, tuple(a.name for a in node.names)))
    _IMPORTS_MEMO[memo_key] = found
    return found


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
        files[_display_path(path, module.split(".")[0])] = hashlib.sha256(path.read_bytes()).hexdigest()
    digest = hashlib.sha256("\n".join(f"{k} {v}" for k, v in sorted(files.items())).encode()).hexdigest()
    return CodeVersion(digest=digest, files=dict(sorted(files.items())))


def clear_memo() -> None:
    """Forget located modules (tests create packages on the fly)."""
    _SPEC_MEMO.clear()
    importlib.invalidate_caches()
