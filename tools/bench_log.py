#!/usr/bin/env python3
"""Benchmark: reading a 10-minute log (600 000 ticks x 4 topics) for ``teleop-rt metrics``.

    python tools/bench_log.py [--ticks N] [--joints N] [--path FILE] [--rebuild] [--sample M]

Builds a synthetic log once (tests/log_fixtures.py: mcap's Writer and LogLayout.encode, 1 MiB
zstd chunks, random fill so it barely compresses: the I/O worst case), then times read_log for
all topics, for /timing alone and for a 10 s window, metrics end to end, and mcap's own
per-message iteration over a log of M ticks (extrapolated to the big one).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from log_fixtures import write_synthetic_log  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

from teleop_rt.recording.metrics import log_metrics, metrics_main  # noqa: E402
from teleop_rt.recording.reader import read_log  # noqa: E402


def best(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ticks", type=int, default=600_000)
    p.add_argument("--joints", type=int, default=2)
    p.add_argument("--path", type=Path, help="log file (default: /tmp/teleop_rt_bench_*.mcap)")
    p.add_argument("--rebuild", action="store_true", help="write the log even if it exists")
    p.add_argument("--sample", type=int, default=50_000, help="ticks of the log mcap iterates")
    args = p.parse_args()
    path = args.path or Path(f"/tmp/teleop_rt_bench_{args.ticks}_{args.joints}j.mcap")
    if args.rebuild or not path.exists():
        t0 = time.perf_counter()
        write_synthetic_log(path, args.ticks, args.joints)
        print(f"wrote {path} in {time.perf_counter() - t0:.1f} s")
    messages = 4 * args.ticks
    print(f"log: {path} ({path.stat().st_size / 1e6:.0f} MB, {args.ticks} ticks, {messages} msgs)")

    def metrics() -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            metrics_main(path)

    data = read_log(path)
    rows = [
        ("read_log, all 4 topics", lambda: read_log(path)),
        ("read_log, /timing only", lambda: read_log(path, ["/timing"])),
        ("read_log, 10 s window", lambda: read_log(path, t_from=100.0, t_to=110.0)),
        ("log_metrics on read data", lambda: log_metrics(data)),
        ("teleop-rt metrics (end to end)", metrics),
    ]
    for what, fn in rows:
        s = best(fn)
        print(f"{what:<34}{s:7.3f} s  ({s / messages * 1e6:.2f} us per message of the log)")

    # mcap's iteration over a whole smaller log of the same kind (with log_time_order=False it
    # still decodes every chunk before yielding the first message, so no early stop)
    small = path.with_name(path.stem + f"_{args.sample}.mcap")
    if args.rebuild or not small.exists():
        write_synthetic_log(small, args.sample, args.joints)
    for order in (False, True):
        with open(small, "rb") as f:
            t0 = time.perf_counter()
            count = sum(1 for _ in make_reader(f).iter_messages(log_time_order=order))
            per = (time.perf_counter() - t0) / count
        print(
            f"{f'mcap iter_messages (order={order})':<34}{per * 1e6:7.2f} us per message -> "
            f"{per * messages:.1f} s for the whole log (for any subset of the topics)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
