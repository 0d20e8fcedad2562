#!/usr/bin/env python3
"""Benchmark: cost of one full simulated tick (both robots' models, controllers, channel, both
plants with their operator / environment) and the fast-mode real-time factor.

    python tools/bench_tick.py [CONFIG] [--ticks N] [--repeat R] [--set key=value ...]

Prints min / median / p99 of the per-tick time over R repeats of N ticks, and the real-time
factor (simulated time / wall time) of the best repeat. Shared machines are noisy: compare
figures from one run, not across runs.
"""

from __future__ import annotations

import argparse
import gc
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.errors import TeleopError  # noqa: E402
from teleop_rt.session import Session  # noqa: E402


def bench(cfg_path: Path, ticks: int, overrides: list[str]) -> tuple[np.ndarray, float]:
    session = Session(config.load(cfg_path, overrides))
    per_tick = np.zeros(ticks, dtype=np.int64)
    perf = time.perf_counter_ns
    gc.collect()
    gc.disable()
    try:
        start = perf()
        for k in range(ticks):
            t0 = perf()
            session.step()
            per_tick[k] = perf() - t0
        wall = (perf() - start) / 1e9
    finally:
        gc.enable()
    return per_tick / 1e3, ticks * session.dt / wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "configs/paper_experiment.yaml"))
    parser.add_argument("--ticks", type=int, default=10_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args()
    print(
        f"machine: {platform.processor() or platform.machine()}, Python {platform.python_version()}"
    )
    print(f"config: {args.config}  ticks: {args.ticks} x {args.repeat}")
    try:
        runs = [bench(Path(args.config), args.ticks, args.overrides) for _ in range(args.repeat)]
    except TeleopError as err:
        print(f"bench_tick: error: {err}", file=sys.stderr)
        return 2
    medians = [float(np.median(t)) for t, _ in runs]
    best = int(np.argmin(medians))
    times, rtf = runs[best]
    print(
        f"full simulated tick (us): min {times.min():.1f}  median {np.median(times):.1f}  "
        f"p99 {np.percentile(times, 99):.1f}   (medians of repeats: "
        f"{', '.join(f'{m:.1f}' for m in medians)}; spread {statistics.pstdev(medians):.1f})"
    )
    print(f"real-time factor (fast mode): {rtf:.1f}x   (1 kHz needs >= 1x; floor of issue #2: 20x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
