"""Side by side against one at a time: the relation and facing stages of the quick profile, trained for a few epochs
on the quick data, (a) one after the other on two threads each (``pipeline.cores=1``, how the pipeline ran them
before) and (b) side by side on one thread each (the default on a host of two cores, ``pipeline/schedule.py``).
Prints each variant's wall time for the pair (a: the two stages' times added; b: the wave's, the longer of the two)
and b/a: below 1, side by side pays on this host.

The variants alternate (a, b, a, b, ...) so that a change of load on a shared machine hits both; the ratio is of the
medians. The data and priors are generated once, before the first timing, in a cache of the benchmark's own.
Run it on an otherwise idle host: a third CPU-bound process makes either variant wait for a core.

    python -m benchmarks.bench_side_by_side [--repeats N] [--relation-epochs E] [--facing-epochs E] [--precision P]
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

from pipeline.schedule import host_cores

REPO = Path(__file__).resolve().parents[1]
VARIANTS = {
    "one at a time, two threads each": ["pipeline.cores=1", "relation.train.threads=2", "facing.train.threads=2"],
    "side by side, one thread each": ["pipeline.cores=2", "relation.train.threads=1", "facing.train.threads=1"],
}


def _pipeline(root: Path, overrides: list[str], timeout: float) -> dict:
    run_dir = root / f"run{time.monotonic_ns()}"
    cmd = [sys.executable, "-m", "pipeline", f"pipeline.cache_dir={root / 'cache'}",
           f"tracking.uri=sqlite:///{root / 'mlflow.db'}", f"hydra.run.dir={run_dir}", "pipeline.estimate=false",
           *overrides]
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "DEEPWORD_CACHE")}
    done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(overrides)} failed ({done.returncode}): {(done.stdout + done.stderr)[-1500:]}")
    return json.loads((run_dir / "summary.json").read_text())


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1, help="timings per variant (alternating)")
    parser.add_argument("--relation-epochs", type=int, default=2, help="epochs of each relation network")
    # with the default relation epochs the two stages take about as long side by side, as in the quick run (four
    # relation networks of ~10 epochs each, 20 facing epochs)
    parser.add_argument("--facing-epochs", type=int, default=5, help="epochs of the facing network")
    parser.add_argument("--precision", default=None,
                        help="trainer.precision for both (e.g. 32-true: fp32, as on a host without bf16)")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per pipeline run")
    args = parser.parse_args(argv)
    if host_cores() < 2:
        print("side by side needs two cores; this host has one")
        return {}
    budget = [f"relation.train.epochs={args.relation_epochs}", f"facing.train.epochs={args.facing_epochs}",
              "pipeline.skip=[shift_data,detector,export]"]  # export out: evaluate and bev, which need it, too
    if args.precision:
        budget.append(f"trainer.precision={args.precision}")
    times: dict[str, list[float]] = {name: [] for name in VARIANTS}
    with tempfile.TemporaryDirectory(prefix="bench_side_by_side_") as tmp:
        root = Path(tmp)
        start = time.perf_counter()
        _pipeline(root, ["pipeline.until=priors"], args.timeout)
        print(f"quick data and priors generated in {time.perf_counter() - start:.0f} s (not timed below)", flush=True)
        for repeat in range(args.repeats):
            for name, overrides in VARIANTS.items():
                summary = _pipeline(root, [*budget, *overrides, "pipeline.force=[relation,facing]"], args.timeout)
                seconds = {s: summary["stages"][s]["seconds"] for s in ("relation", "facing")}
                pair = max(seconds.values()) if "side by side" in name else sum(seconds.values())
                times[name].append(pair)
                print(f"  {name:<32} relation {seconds['relation']:6.1f} s, facing {seconds['facing']:6.1f} s: "
                      f"the pair {pair:6.1f} s  (repeat {repeat + 1}, load {os.getloadavg()[0]:.1f})", flush=True)
    medians = {name: statistics.median(t) for name, t in times.items()}
    (one, both) = medians.values()
    print(f"relation and facing ({args.relation_epochs} and {args.facing_epochs} epochs, precision "
          f"{args.precision or 'auto'}): one at a time {one:.1f} s, "
          f"side by side {both:.1f} s; side by side / one at a time = {both / one:.2f}")
    return medians


if __name__ == "__main__":
    main()
