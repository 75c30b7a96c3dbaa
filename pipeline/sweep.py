"""The summary of a Hydra multirun sweep: per job, which stages were computed and which were cache hits.

Every job of a sweep writes the engine's ``summary.json`` in its own directory (``<sweep dir>/<job num>``).
This module reads them back and writes ``<sweep dir>/sweep_summary.json`` plus a printed table, so a
user sees that the stages the jobs share (data, priors) were computed once for the whole
sweep and only the stages the swept options change ran in every job.

Hydra calls ``SweepSummary.on_multirun_end`` when a sweep ends (``hydra.callbacks`` in the experiment
configs); ``python -m pipeline.sweep <sweep dir>`` summarises an existing sweep directory again.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from hydra.experimental.callback import Callback

from pipeline.mlflow_ops import MlflowOps

SUMMARY_FILE = "summary.json"
SWEEP_SUMMARY_FILE = "sweep_summary.json"


def _job_overrides(job_dir: Path) -> list[str]:
    """The job's own overrides from Hydra's ``.hydra/overrides.yaml`` (a YAML list of strings)."""
    path = job_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return []
    return [line[2:].strip() for line in path.read_text().splitlines() if line.startswith("- ")]


def _job_number(job_dir: Path) -> tuple[int, str]:
    return (int(job_dir.name), "") if job_dir.name.isdigit() else (sys.maxsize, job_dir.name)


def read_jobs(sweep_dir: Path) -> list[dict]:
    """One record per job directory holding a summary.json, in job order."""
    jobs = []
    for path in sorted(Path(sweep_dir).glob(f"*/{SUMMARY_FILE}"), key=lambda p: _job_number(p.parent)):
        summary = json.loads(path.read_text())
        jobs.append({
            "job": path.parent.name,
            "overrides": _job_overrides(path.parent),
            "mlflow_run_id": summary.get("mlflow_run_id"),
            "pipeline_seconds": summary.get("pipeline_seconds"),
            "stages": {
                name: {"hit": bool(s["hit"]), "key": s["key"], "reason": s.get("reason", ""),
                       "seconds": s.get("seconds"), "computed_by_run": s.get("computed_by_run", "")}
                for name, s in summary.get("stages", {}).items()
            },
        })
    return jobs


def stage_totals(jobs: list[dict]) -> dict[str, dict]:
    """Per stage: how many jobs used it, how many distinct cache entries, how many were computed here."""
    totals: dict[str, dict] = {}
    for job in jobs:
        for name, s in job["stages"].items():
            t = totals.setdefault(name, {"jobs": 0, "keys": set(), "computed": 0})
            t["jobs"] += 1
            t["keys"].add(s["key"])
            t["computed"] += 0 if s["hit"] else 1
    return {name: {"jobs": t["jobs"], "distinct_keys": len(t["keys"]), "computed": t["computed"],
                   "reused": t["jobs"] - t["computed"]} for name, t in totals.items()}


def swept_overrides(job: dict, jobs: list[dict]) -> list[str]:
    """The job's overrides that not every job shares: what the sweep varied."""
    common = set.intersection(*(set(j["overrides"]) for j in jobs))
    return [o for o in job["overrides"] if o not in common]


def format_table(jobs: list[dict], totals: dict[str, dict]) -> str:
    """Rows = jobs, columns = stages; 'run' = computed by this job, 'hit' = an entry another job (or an
    earlier run) computed."""
    stages = list(totals)
    labels = [" ".join(swept_overrides(j, jobs)) or "(defaults)" for j in jobs]
    width = max([len("job  overrides"), *(len(j["job"]) + 2 + len(lab) for j, lab in zip(jobs, labels, strict=True))])
    lines = ["  ".join([f"{'job  overrides':<{width}}", *(f"{s:>9}" for s in stages), f"{'seconds':>8}"])]
    for job, label in zip(jobs, labels, strict=True):
        cells = []
        for s in stages:
            st = job["stages"].get(s)
            cells.append(f"{'-' if st is None else ('hit' if st['hit'] else 'run'):>9}")
        seconds = job["pipeline_seconds"] or 0.0
        lines.append("  ".join([f"{job['job'] + '  ' + label:<{width}}", *cells, f"{seconds:>8.1f}"]))
    lines.append("  ".join([f"{'computed / jobs':<{width}}",
                            *(f"{str(totals[s]['computed']) + '/' + str(totals[s]['jobs']):>9}" for s in stages)]))
    return "\n".join(lines)


def summarize(sweep_dir: Path) -> dict:
    """Write ``sweep_summary.json`` into ``sweep_dir``, print the table and return the summary."""
    sweep_dir = Path(sweep_dir)
    jobs = read_jobs(sweep_dir)
    totals = stage_totals(jobs)
    summary = {"sweep_dir": str(sweep_dir), "jobs": jobs, "stages": totals}
    (sweep_dir / SWEEP_SUMMARY_FILE).write_text(json.dumps(summary, indent=2))
    common = [o for o in jobs[0]["overrides"] if all(o in j["overrides"] for j in jobs)] if jobs else []
    print(f"Sweep {sweep_dir}: {len(jobs)} job(s) with {' '.join(common) or 'no common overrides'}")
    print("'run' = computed by that job, 'hit' = a cache entry another job or an earlier run computed")
    print(format_table(jobs, totals), flush=True)
    return summary


def prepare_tracking_store(uri: str, experiment: str) -> None:
    """Create the MLflow store's tables and the experiment before the jobs start: parallel jobs that
    each create a fresh sqlite store race on its schema migration and one of them fails."""

    MlflowOps(uri, experiment)


class SweepSummary(Callback):
    """Hydra callback: prepare the tracking store before the jobs start; summarise the sweep when it ends
    (the jobs' summaries are all written by then)."""

    def on_multirun_start(self, config, **kwargs) -> None:
        prepare_tracking_store(str(config.tracking.uri), str(config.tracking.get("experiment", "deepword")))

    def on_multirun_end(self, config, **kwargs) -> None:
        summarize(Path(str(config.hydra.sweep.dir)))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m pipeline.sweep <sweep dir>")
    summarize(Path(sys.argv[1]))
