"""Synthetic data generation speed: images per second, and the projected time of the full profile's
9,000 images (2,250 frames x 4 cameras) on 2 cores against its 10-minute target.

Frames are rendered in this process (no pool) and timed by both wall clock and this process' CPU time:
on a shared machine the CPU time gives the per-core rate the wall clock hides; the projection assumes
two cores each running at that rate (generation is embarrassingly parallel across frames).

    python -m benchmarks.bench_data [--frames N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from omegaconf import OmegaConf

from stages.data.synword import FrameGenerator, write_frame

CONF = Path(__file__).resolve().parents[1] / "conf" / "data" / "synword.yaml"
FULL_RENDERS = 9000
TARGET_S = 600.0
CORES = 2


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=24)
    args = parser.parse_args(argv)
    cfg = OmegaConf.to_container(OmegaConf.load(CONF), resolve=True)
    cfg["frames"] = args.frames
    gen = FrameGenerator(cfg, seed=0)  # per-process set-up (ray tables), paid once per worker
    kept = 0
    with tempfile.TemporaryDirectory() as tmp:
        wall, cpu = time.perf_counter(), time.process_time()
        for frame in range(args.frames):
            kept += len(write_frame(gen, frame, Path(tmp)))
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    renders = 4 * args.frames  # every camera is rendered and labelled; images without relations are dropped
    per_core = renders / cpu
    projected = FULL_RENDERS / (CORES * per_core)
    w, h = cfg["image_size"]
    print(f"bench_data: {renders} renders ({kept} kept) around {w}x{h} (lens and size drawn per camera): {renders / wall:.1f} images/s wall, "
          f"{per_core:.1f} images/s per CPU-second (one process)")
    print(f"bench_data: projected full profile ({FULL_RENDERS} images) on {CORES} cores: {projected:.0f} s = "
          f"{projected / TARGET_S:.2f} x the {TARGET_S:.0f} s target")
    return {"images_per_s_wall": renders / wall, "images_per_cpu_s": per_core, "projected_full_s": projected}


if __name__ == "__main__":
    main()
