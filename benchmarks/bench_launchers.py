"""Sweep launchers: the same two-job smoke sweep (``experiment=table1 profile=smoke``: Conv+fc and ResNet-18
rows, data and priors shared through the stage cache) run by hydra-joblib-launcher (``local_parallel``, the
default) and by hydra-submitit-launcher's local executor (``submitit_local``, each job a process of its own
as on SLURM), each on a fresh cache and MLflow store. Prints each wall time and submitit/joblib: the price
of submitit's job processes, pickling and result polling against joblib's workers.

The two launchers alternate (joblib first, then submitit, then again) so that a change of load on a shared
machine hits both; the ratio printed is of the medians.

    python -m benchmarks.bench_launchers [--repeats N] [--until STAGE] [--timeout S]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAUNCHERS = ("local_parallel", "submitit_local")


def run_sweep(launcher: str, until: str | None, timeout: float) -> dict:
    """One sweep on a fresh cache and store: wall seconds and how many jobs computed each stage."""
    with tempfile.TemporaryDirectory(prefix="bench_launchers_") as tmp:
        root = Path(tmp)
        cmd = [sys.executable, "-m", "pipeline", "experiment=table1", "profile=smoke", f"hydra/launcher={launcher}",
               f"pipeline.cache_dir={root / 'cache'}", f"tracking.uri=sqlite:///{root / 'mlflow.db'}",
               f"hydra.sweep.dir={root / 'sweep'}"]
        if until:
            cmd.append(f"pipeline.until={until}")
        env = {**os.environ, "DEEPWORD_THREADS": "1"}
        env.pop("MLFLOW_TRACKING_URI", None)
        start = time.perf_counter()
        done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
        seconds = time.perf_counter() - start
        if done.returncode != 0:
            raise RuntimeError(f"{launcher} sweep failed ({done.returncode}): {(done.stdout + done.stderr)[-1500:]}")
        summary = json.loads((root / "sweep" / "sweep_summary.json").read_text())
    computed = {stage: f"{t['computed']}/{t['jobs']}" for stage, t in summary["stages"].items()}
    return {"seconds": seconds, "computed": computed, "load": os.getloadavg()[0]}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1, help="sweeps per launcher (alternating)")
    parser.add_argument("--until", default=None, help="pipeline.until for both sweeps (default: every stage)")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per sweep")
    args = parser.parse_args(argv)
    times: dict[str, list[float]] = {name: [] for name in LAUNCHERS}
    for _ in range(args.repeats):
        for name in LAUNCHERS:
            result = run_sweep(name, args.until, args.timeout)
            times[name].append(result["seconds"])
            print(f"{name}: two-job smoke sweep {result['seconds']:.1f} s; computed/jobs per stage {result['computed']} "
                  f"(load average {result['load']:.1f} on {os.cpu_count()} cores)", flush=True)
    medians = {name: statistics.median(values) for name, values in times.items()}
    ratio = medians["submitit_local"] / medians["local_parallel"]
    print(f"submitit_local / local_parallel (joblib), medians of {args.repeats}: {ratio:.2f}x "
          f"({medians['submitit_local']:.1f} s vs {medians['local_parallel']:.1f} s)", flush=True)
    return {"seconds": times, "ratio": ratio}


if __name__ == "__main__":
    main()
