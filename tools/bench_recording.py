#!/usr/bin/env python3
"""Benchmark: what per-tick recording costs the control process in fast mode.

    python tools/bench_recording.py [CONFIG] [--ticks N] [--repeat R]

Runs the same session with and without a recorder, alternating, and prints the wall time per
tick of each and their difference (the amortized cost of recording, including the wait for the
writer process to finish the file), plus the cost of the hot-path call alone.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.recording.recorder import Recorder  # noqa: E402
from teleop_rt.session import Session  # noqa: E402


def one_run(cfg, ticks: int, log: Path | None) -> tuple[float, float]:
    session = Session(cfg)
    recorder = Recorder(session, log) if log else None
    hot = []
    if recorder is not None:  # time the hot-path call itself on a copy of the loop
        original = recorder.record

        def timed(*a):
            t0 = time.perf_counter_ns()
            original(*a)
            hot.append(time.perf_counter_ns() - t0)

        recorder.record = timed
    start = time.perf_counter_ns()
    session.run(ticks=ticks, recorder=recorder)  # includes closing the log
    per_tick = (time.perf_counter_ns() - start) / ticks / 1e3
    return per_tick, (float(np.median(hot)) / 1e3 if hot else 0.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", default=str(ROOT / "configs/paper_experiment.yaml"))
    parser.add_argument("--ticks", type=int, default=12_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    cfg = config.load(args.config)
    plain, logged, hot = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            plain.append(one_run(cfg, args.ticks, None)[0])
            t, h = one_run(cfg, args.ticks, Path(tmp) / f"bench-{r}.mcap")
            logged.append(t)
            hot.append(h)
    p, lg = float(np.median(plain)), float(np.median(logged))
    print(f"config: {args.config}  ticks: {args.ticks} x {args.repeat} (alternating)")
    runs_plain = ", ".join(f"{x:.1f}" for x in plain)
    runs_logged = ", ".join(f"{x:.1f}" for x in logged)
    print(f"wall per tick without recording: {p:.1f} us  (runs: {runs_plain})")
    print(f"wall per tick with recording:    {lg:.1f} us  (runs: {runs_logged})")
    print(f"recording cost, amortized:       {lg - p:.1f} us per tick (target <= 5 us)")
    print(f"hot-path record() call, median:  {float(np.median(hot)):.2f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
