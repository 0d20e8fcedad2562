#!/usr/bin/env python3
"""Instructions per tick, counted by valgrind's callgrind: a figure that does not move with the
machine's load (wall-clock medians on a shared VM swing by 2x; instruction counts repeat).

    python tools/bench_instructions.py [CONFIG] [--ticks N] [--json OUT]

For the full simulated tick (recording off, then on) and the controller-side tick (feedback
replayed, no plant, as in tools/bench.py) it runs the session twice under callgrind, with N
ticks and with none after the same set-up and warm-up, and divides the difference by N. The count is
split by where the instructions ran: the Python interpreter, Pinocchio with its bindings
(boost.python, eigenpy), numpy, the C library, other extension modules. Use it to judge a
change to the tick path: a few hundred instructions are visible, where wall-clock timing on
this machine hides 10 %. With recording on, only the control process is counted (the hot-path
``Recorder.record``), not the writer process beside it. Needs valgrind on PATH (Debian package
``valgrind``); about a minute per mode, or several on a busy machine: progress goes to stderr
(a line per run started and finished, with the time taken; on a terminal a live timer too).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs/paper_experiment.yaml"
WARMUP_TICKS = 200
MODES = {
    "full": "full tick (recording off)",
    "recording": "full tick, recording on (this process; the writer runs in its own)",
    "controller": "controller side (no plant)",
}
# where instructions ran, by the shared object that holds them (first match wins)
CATEGORIES = (
    ("interpreter", ("libpython",)),
    ("Pinocchio + bindings", ("pinocchio", "boost_python", "eigenpy", "coal", "hpp-fcl")),
    ("numpy", ("_multiarray", "numpy", "openblas")),
    ("C library", ("libc.so", "libm.so", "ld-linux")),
)
OTHER = "other extension modules"


def child(config: Path, mode: str, ticks: int, samples: int) -> None:
    """The measured process: build the session, warm up, run ``ticks`` ticks. The controller
    side replays ``samples`` ticks of feedback recorded from a full session (the same number in
    both runs, so that recording cancels out of the difference)."""
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "tools"))
    from teleop_rt import config as config_module
    from teleop_rt.session import Session

    cfg = config_module.load(config)
    session = Session(cfg)
    if mode == "controller":
        import bench

        session = bench.replayed_session(cfg, bench.record_feedback(cfg, samples))
    step = session.step
    if mode == "recording":  # the hot-path call of Session.run with a recorder
        import tempfile

        from teleop_rt.recording.recorder import Recorder

        log_dir = Path(tempfile.mkdtemp())
        recorder = Recorder(session, log_dir / "bench.mcap")
        record = recorder.record

        def step() -> None:
            session.step()
            record(0, 0, False)

    for _ in range(WARMUP_TICKS):
        step()
    for _ in range(ticks):
        step()
    if mode == "recording":
        recorder.close(None)
        shutil.rmtree(log_dir)


def instructions_by_object(callgrind_out: Path) -> Counter:
    """Self cost (Ir) per shared object from a callgrind output file (name compression
    resolved; the inclusive cost lines after ``calls=`` are skipped)."""
    names: dict[str, str] = {}  # compressed object ids (ob= and cob= share them)
    totals: Counter = Counter()
    obj = "?"
    after_call = False
    pattern = re.compile(r"\((\d+)\)(?: (.*))?")
    for line in callgrind_out.read_text(errors="replace").splitlines():
        if not line:
            continue
        head = line[0]
        if head.isdigit() or head in "+-*":
            if after_call:
                after_call = False
                continue
            parts = line.split()
            if len(parts) > 1:
                totals[obj] += int(parts[1])
        elif line.startswith(("ob=", "cob=")):
            key, value = line.split("=", 1)
            m = pattern.match(value)
            if m:  # "(id) name" defines the id, "(id)" reuses it
                name = m.group(2) if m.group(2) is not None else names.get(m.group(1), "?")
                names[m.group(1)] = name
            else:
                name = value
            if key == "ob":
                obj = name
        elif line.startswith("calls="):
            after_call = True
    return totals


def categorise(by_object: Counter) -> Counter:
    out: Counter = Counter()
    for obj, count in by_object.items():
        base = Path(obj).name
        out[next((c for c, keys in CATEGORIES if any(k in base for k in keys)), OTHER)] += count
    return out


def count(config: Path, mode: str, ticks: int, samples: int, tmp: Path) -> Counter:
    """Callgrind self cost per category for ``ticks`` ticks of ``mode``."""
    # %p: a forked log writer writes its own file; the measured process is the one started
    cmd = [
        "valgrind", "--tool=callgrind", f"--callgrind-out-file={tmp}/{mode}-{ticks}.%p.out",
        "--child-silent-after-fork=yes",
        sys.executable, __file__, "--child", mode, "--ticks", str(ticks),
        "--samples", str(samples), str(config),
    ]  # fmt: skip
    # one OpenBLAS thread: its idle threads spin for a varying number of instructions
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    _, stderr = proc.communicate()
    if proc.returncode != 0:
        last = (stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"{mode} under callgrind failed: {last}")
    return categorise(instructions_by_object(tmp / f"{mode}-{ticks}.{proc.pid}.out"))


@contextmanager
def working(what: str) -> Iterator[None]:
    """Say on stderr what runs and, when it ends, how long it took; on a terminal the line
    also counts the seconds while it runs."""
    start = time.monotonic()
    done = threading.Event()
    live = sys.stderr.isatty()

    def tick() -> None:
        while not done.wait(1.0):
            print(f"\r{what} ... {time.monotonic() - start:.0f} s", end="", file=sys.stderr)

    print(f"{what} ...", end="" if live else "\n", file=sys.stderr, flush=True)
    timer = threading.Thread(target=tick, daemon=True) if live else None
    if timer:
        timer.start()
    try:
        yield
    finally:
        done.set()
        if timer:
            timer.join()
        took = f"{what}: done in {time.monotonic() - start:.0f} s"
        print(f"\r{took}" if live else took, file=sys.stderr, flush=True)


def per_tick(config: Path, mode: str, ticks: int, tmp: Path) -> dict[str, float]:
    with ThreadPoolExecutor(2) as pool:  # the two runs in parallel (2 cores)
        samples = WARMUP_TICKS + ticks
        runs = pool.map(lambda n: count(config, mode, n, samples, tmp), (ticks, 0))
        with_ticks, without = runs
    return {k: (with_ticks[k] - without[k]) / ticks for k in with_ticks | without}


def main() -> int:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "config", nargs="?", type=Path, default=PAPER, help="session config (default: the paper's)"
    )
    parser.add_argument(
        "--ticks",
        type=int,
        default=2000,
        metavar="N",
        help="ticks counted per mode, after the warm-up (default 2000, at least 100)",
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="also write the figures as JSON")
    parser.add_argument("--child", choices=sorted(MODES), help=argparse.SUPPRESS)
    parser.add_argument("--samples", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.config, args.child, args.ticks, args.samples)
        return 0
    if args.ticks < 100:
        print("bench_instructions: error: --ticks must be >= 100", file=sys.stderr)
        return 2
    if not args.config.is_file():
        print(f"bench_instructions: error: no such config: {args.config}", file=sys.stderr)
        return 2
    if shutil.which("valgrind") is None:
        print("bench_instructions: error: valgrind is not on PATH (apt install valgrind)",
              file=sys.stderr)  # fmt: skip
        return 2
    print(f"config: {args.config}   {args.ticks} ticks after {WARMUP_TICKS} of warm-up, "
          "under callgrind (instructions per tick)")  # fmt: skip
    results = {}
    with tempfile.TemporaryDirectory() as tmp_name:
        for i, (mode, label) in enumerate(MODES.items(), 1):
            what = f"[{i}/{len(MODES)}] {label}: {args.ticks} ticks and 0 under callgrind"
            try:
                with working(what):
                    results[mode] = per_tick(args.config, mode, args.ticks, Path(tmp_name))
            except RuntimeError as err:
                print(f"bench_instructions: error: {err}", file=sys.stderr)
                return 1
            total = sum(results[mode].values())
            print(f"\n{label}: {total:,.0f} instructions per tick")
            for cat in [c for c, _ in CATEGORIES] + [OTHER]:
                share = results[mode].get(cat, 0.0)
                print(f"  {cat:<26} {share:10,.0f}  {100 * share / total:5.1f} %")
    added = sum(results["recording"].values()) - sum(results["full"].values())
    print(f"\nrecording adds {added:,.0f} instructions per tick to the control process "
          "(Recorder.record; the writer process is not counted)")  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
