"""Run every ``benchmarks/bench_*.py`` module's ``main()`` in turn (or only those named):

    python -m benchmarks                 # all
    python -m benchmarks noop data       # bench_noop.py and bench_data.py only

Each benchmark runs with its default arguments; run one directly for its options
(``python -m benchmarks.bench_noop --help``). A failing benchmark is reported and the others still run.
"""

from __future__ import annotations

import importlib
import sys
import time
import traceback
from pathlib import Path


def discover() -> list[str]:
    return sorted(p.stem for p in Path(__file__).resolve().parent.glob("bench_*.py"))


def main(argv: list[str] | None = None) -> int:
    wanted = argv if argv is not None else sys.argv[1:]
    names = [n for n in discover() if not wanted or n.removeprefix("bench_") in wanted or n in wanted]
    failed = []
    for name in names:
        print(f"\n=== {name} ===", flush=True)
        start = time.perf_counter()
        try:
            importlib.import_module(f"benchmarks.{name}").main([])
        except Exception:
            traceback.print_exc()
            failed.append(name)
        print(f"=== {name}: {time.perf_counter() - start:.1f} s ===", flush=True)
    if failed:
        print(f"\nfailed benchmarks: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
