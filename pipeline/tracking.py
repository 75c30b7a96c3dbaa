"""What stage code may ask the engine about tracking. Deliberately tiny and import-free, because every
stage importing it includes this file in its code version.
"""

from __future__ import annotations

_active: tuple[str, str] | None = None


def stage_run_info() -> tuple[str, str] | None:
    """(tracking_uri, run_id) of the MLflow child run of the stage now running, or None outside a
    pipeline (unit tests). Use it for Lightning: ``MLFlowLogger(tracking_uri=uri, run_id=run_id)``."""
    return _active


def set_active(info: tuple[str, str] | None) -> None:
    """Engine only: mark the child run of the stage about to run (None when it ends)."""
    global _active
    _active = info
