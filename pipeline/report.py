"""The run's ``summary.json`` and the compact table printed at the end."""

from __future__ import annotations

import json
from pathlib import Path

MAIN_METRICS = 3


def write_summary(run_dir: Path, summary: dict) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / "summary.json"
    path.write_text(json.dumps(summary, indent=2, sort_keys=False, allow_nan=True))
    return path


def _main_metrics(metrics: dict[str, float]) -> str:
    shown = list(metrics.items())[:MAIN_METRICS]
    text = ", ".join(f"{k}={v:.4g}" for k, v in shown)
    more = len(metrics) - len(shown)
    return text + (f" (+{more} more)" if more > 0 else "")


def summary_table(summary: dict) -> str:
    stages, not_run = summary["stages"], summary.get("not_run", {})
    width = max([len("stage"), *(len(n) for n in [*stages, *not_run])])
    lines = [f"{'stage':<{width}}  {'cache':<5}  {'seconds':>8}  {'key':<10}  metrics"]
    for name, s in stages.items():
        lines.append(
            f"{name:<{width}}  {'hit' if s['hit'] else 'miss':<5}  {s['seconds']:>8.2f}  {s['key'][:10]}  "
            f"{_main_metrics(s['metrics'])}"
        )
    lines += [f"{name:<{width}}  {'-':<5}  {'':>8}  {'':<10}  not run: {why}" for name, why in not_run.items()]
    lines += figure_lines(summary)
    lines.append(f"pipeline: {summary['pipeline_seconds']:.2f} s; MLflow run {summary['mlflow_run_id']}")
    return "\n".join(lines)


def figure_lines(summary: dict, shown: int = 3) -> list[str]:
    """Where each stage's figures are: the PNG files at the top of its ``artifacts`` folder."""
    lines = []
    for name, s in summary["stages"].items():
        folder = Path(s.get("output_dir") or "") / "artifacts"
        pngs = sorted(p.name for p in folder.glob("*.png")) if s.get("output_dir") and folder.is_dir() else []
        if pngs:
            more = f", ... ({len(pngs)} figures)" if len(pngs) > shown else ""
            lines.append(f"  {name}: {folder}/{{{', '.join(pngs[:shown])}{more}}}")
    return ["figures:", *lines] if lines else []
