"""No-op re-run time (docs/design.md §9: an all-hit re-run <= 3 s wall; warm <= 10 % of cold), and the
all-hit re-run beside `python -c "import mlflow"` on the same host (docs/engine.md, "Tracking").

1. A toy six-stage DAG shaped like the real one (data -> priors -> relation -> export -> evaluate, and
   detector), each stage a few milliseconds, run through the real CLI (`python -m pipeline` with
   `--config-path`) in subprocesses: cold, then warm (all hits) twice. The warm time is what the engine
   itself costs: the cold run recorded the run in MLflow, so the warm runs name it and log nothing.
2. The real pipeline, `python -m pipeline profile=smoke` (or the default `quick` profile, what
   `make pipeline` runs, with `--real`), cold, in a temporary cache and MLflow store; then, `--repeats`
   times in turn, `python -c "import mlflow"` and the all-hit re-run: their medians and the ratio
   (re-run / import; below 1 the re-run is the faster). Skipped with a message if it cannot run (stages
   missing or failing).

    python -m benchmarks.bench_noop [--real] [--no-real] [--repeats N] [--timeout S]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 3.0
TOY_STAGES = {  # name: inputs, like docs/design.md §1
    "data": [], "priors": ["data"], "detector": ["data"], "relation": ["data", "priors"],
    "export": ["detector", "relation"], "evaluate": ["data", "priors", "relation", "detector"],
}
TOY_STAGE_CODE = '''
def run(cfg, inputs, out_dir):
    total = sum(int((p / "n.txt").read_text()) for p in inputs.values()) + cfg.toy.size
    (out_dir / "n.txt").write_text(str(total))
    return {"%(name)s.total": float(total)}
'''


def _write_toy(root: Path) -> Path:
    pkg = root / "noopbench"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for name in TOY_STAGES:
        (pkg / name).mkdir()
        (pkg / name / "__init__.py").write_text("")
        (pkg / name / "stage.py").write_text(TOY_STAGE_CODE % {"name": name})
    stages = "\n".join(
        f"    {name}: {{run: 'noopbench.{name}.stage:run', inputs: {inputs}, config: [toy, seed]}}"
        for name, inputs in TOY_STAGES.items()
    )
    conf = root / "conf"
    conf.mkdir()
    (conf / "noop.yaml").write_text(
        "seed: 1\nprofile_name: bench\ntoy: {size: 1}\n"
        f"tracking: {{uri: 'sqlite:///{root}/mlflow.db', experiment: bench, require_server: false}}\n"
        "pipeline:\n  cache_dir: cache\n  force: []\n  until: null\n  stages:\n" + stages + "\n"
        "hydra:\n  job: {chdir: false}\n  run: {dir: 'runs/${now:%H-%M-%S-%f}'}\n"
    )
    return conf


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _timed(cmd: list[str], cwd: Path, env: dict, timeout: float) -> tuple[float, float, subprocess.CompletedProcess]:
    """(wall s, CPU s of the run and its children, result). CPU time shows the cost a loaded machine hides."""
    cpu0, start = _children_cpu(), time.perf_counter()
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    return time.perf_counter() - start, _children_cpu() - cpu0, done


def _cold_warm(cmd: list[str], cwd: Path, env: dict, timeout: float, warm_runs: int) -> dict:
    cold, cold_cpu, done = _timed(cmd, cwd, env, timeout)
    if done.returncode != 0:
        raise RuntimeError(f"exit {done.returncode}: {(done.stdout + done.stderr)[-1500:]}")
    warms, cpus = [], []
    for _ in range(warm_runs):
        seconds, cpu, done = _timed(cmd, cwd, env, timeout)
        if done.returncode != 0 or "Pipeline up to date." not in done.stdout:
            raise RuntimeError(f"warm run was not all hits: {(done.stdout + done.stderr)[-1500:]}")
        warms.append(seconds)
        cpus.append(cpu)
    return {"cold_s": cold, "cold_cpu_s": cold_cpu, "warm_s": min(warms), "warm_all_s": warms,
            "warm_cpu_s": min(cpus), "load": os.getloadavg()[0]}


def _report(label: str, r: dict) -> None:
    ratio = r["warm_s"] / r["cold_s"]
    verdict = "OK" if r["warm_s"] <= TARGET_S else "OVER"
    print(f"{label}: cold {r['cold_s']:.2f} s, warm (no-op) {r['warm_s']:.2f} s "
          f"(runs: {', '.join(f'{s:.2f}' for s in r['warm_all_s'])}); warm/cold = {ratio:.1%}; "
          f"no-op vs {TARGET_S:.0f} s target: {verdict} ({r['warm_s'] / TARGET_S:.2f}x); CPU s cold "
          f"{r['cold_cpu_s']:.2f}, warm {r['warm_cpu_s']:.2f} (load average {r['load']:.1f} on "
          f"{os.cpu_count()} cores: wall times stretch under load, CPU times do not)", flush=True)


def bench_toy(timeout: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_noop_") as tmp:
        root = Path(tmp)
        conf = _write_toy(root)
        env = {**os.environ, "PYTHONPATH": f"{root}{os.pathsep}{REPO}"}
        cmd = [sys.executable, "-m", "pipeline", "--config-path", str(conf), "--config-name", "noop"]
        result = _cold_warm(cmd, root, env, timeout, warm_runs=2)
    _report("toy 6-stage DAG (python -m pipeline, MLflow sqlite)", result)
    return result


def _side_by_side(cmd: list[str], cwd: Path, env: dict, timeout: float, repeats: int) -> dict:
    """`import mlflow` and the all-hit re-run ``cmd``, alternately, ``repeats`` times each: the host's load
    drifts, so each pair sees about the same."""
    importing = [sys.executable, "-c", "import mlflow"]
    imports, reruns, recorded = [], [], 0
    for _ in range(repeats):
        seconds, _cpu, done = _timed(importing, cwd, env, timeout)
        if done.returncode != 0:
            raise RuntimeError(f"import mlflow failed: {done.stderr[-800:]}")
        imports.append(seconds)
        seconds, _cpu, done = _timed(cmd, cwd, env, timeout)
        if done.returncode != 0 or "Pipeline up to date." not in done.stdout:
            raise RuntimeError(f"re-run was not all hits: {(done.stdout + done.stderr)[-1500:]}")
        recorded += "Already recorded: MLflow run" in done.stdout
        reruns.append(seconds)
    return {"import_s": imports, "rerun_s": reruns, "recorded": recorded, "load": os.getloadavg()[0]}


def _report_side_by_side(label: str, r: dict) -> None:
    imp, rerun = statistics.median(r["import_s"]), statistics.median(r["rerun_s"])
    print(f"{label}: all-hit re-run median {rerun:.2f} s (runs: {', '.join(f'{s:.2f}' for s in r['rerun_s'])}); "
          f"python -c 'import mlflow' median {imp:.2f} s (runs: {', '.join(f'{s:.2f}' for s in r['import_s'])}); "
          f"re-run / import mlflow = {rerun / imp:.2f} ({'faster' if rerun < imp else 'SLOWER'} than importing "
          f"MLflow; {r['recorded']} of {len(r['rerun_s'])} re-runs named the recorded run; load average "
          f"{r['load']:.1f} on {os.cpu_count()} cores)", flush=True)


def bench_real(profile: str | None, timeout: float, repeats: int = 5) -> dict | None:
    with tempfile.TemporaryDirectory(prefix="bench_real_") as tmp:
        root = Path(tmp)
        env = {**os.environ, "DEEPWORD_CACHE": str(root / "cache"), "MLFLOW_TRACKING_URI": f"sqlite:///{root}/mlflow.db"}
        env.pop("PYTHONPATH", None)
        cmd = [sys.executable, "-m", "pipeline", f"hydra.run.dir={root}/runs/${{now:%H-%M-%S-%f}}"]
        if profile:
            cmd.append(f"profile={profile}")
        label = f"real pipeline ({'profile=' + profile if profile else 'default profile, as make pipeline'})"
        try:
            cold, cold_cpu, done = _timed(cmd, REPO, env, timeout)
            if done.returncode != 0:
                raise RuntimeError(f"exit {done.returncode}: {(done.stdout + done.stderr)[-1500:]}")
            result = _side_by_side(cmd, REPO, env, timeout, repeats)
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            print(f"{label}: skipped, it did not run: {str(exc)[-800:]}", flush=True)
            return None
    result.update(cold_s=cold, cold_cpu_s=cold_cpu)
    print(f"{label}: cold {cold:.2f} s (CPU {cold_cpu:.2f} s)", flush=True)
    _report_side_by_side(label, result)
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", action="store_true", help="real pipeline with the default profile, not smoke")
    parser.add_argument("--no-real", action="store_true", help="only the toy DAG")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per real pipeline run")
    parser.add_argument("--repeats", type=int, default=5, help="all-hit re-runs and MLflow imports, each")
    args = parser.parse_args(argv)
    results = {"toy": bench_toy(timeout=300)}
    if not args.no_real:
        results["real"] = bench_real(None if args.real else "smoke", args.timeout, args.repeats)
    return results


if __name__ == "__main__":
    main()
