"""Fresh MLflow sqlite stores for tests, copied from one initialised empty store: MLflow creates a new
store's tables by running every schema migration, 5-10 s per store on 2 cores; a copy takes milliseconds
and is the same empty store (same MLflow version, same schema)."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

_template: Path | None = None


def template() -> Path:
    """The initialised empty store, created once per test session (on first use)."""
    global _template
    if _template is None:
        from mlflow.tracking import MlflowClient

        folder = Path(tempfile.mkdtemp(prefix="mlflow_template_"))
        atexit.register(shutil.rmtree, folder, True)
        path = folder / "mlflow.db"
        MlflowClient(f"sqlite:///{path}").search_experiments()  # creates the tables
        _template = path
    return _template


def fresh_store(path: Path) -> str:
    """An initialised empty MLflow store at ``path`` unless a store is already there; its tracking URI."""
    path = Path(path)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(template(), path)
    return f"sqlite:///{path}"


def fresh_store_for_uri(uri: str) -> None:
    """``fresh_store`` for a ``sqlite:///<absolute path>`` URI; other URIs are left alone."""
    if uri.startswith("sqlite:///"):
        fresh_store(Path(uri[len("sqlite:///"):]))
