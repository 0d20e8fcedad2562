#!/usr/bin/env python3
"""Benchmark: the CAN backend against the drive emulator in another process, in real time.

    python tools/bench_can.py [CONFIG] [--seconds S] [--side hsi|to] [--set key=value ...]
                              [--emulator-realtime] [--emulator-poll-us US]

Starts ``tools/drive_emulator.py`` for one robot (two drives and a torque sensor by default)
over the config's bus (``udp_multicast`` on this host in configs/can_emulated.yaml: hop_limit
0, as for every udp_multicast bus that does not set one), runs the backend's start-up, then
``read`` / ``write`` at the config's rate with absolute deadlines for S seconds (default 60), a
light joint damper as the controller. Prints:

* missed feedback windows: cycles in which some drive's TPDO (or the sensor's) was not in
  within ``feedback_window_us`` after SYNC, and frames that came late;
* master CPU per cycle (thread CPU time of ``read`` + ``write``: p50 / p99 / max) and the
  wall time of the same (it includes the wait for the drives' answers);
* deadline lateness and missed deadlines of the loop;
* the backend's own CPU per cycle without any transport (a bus that hands back the drives'
  frames at once, ``--transport-free-cycles``), to tell the backend's share from the
  interface's.

A safety stop (e.g. 3 missed windows in a row) ends the run early and is reported; raise
``--set can.missed_feedback_ticks=1000`` to measure through them.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.errors import SafetyStop, TeleopError  # noqa: E402
from teleop_rt.hal.registry import create_backend  # noqa: E402
from teleop_rt.loop import TickClock, acquire_realtime  # noqa: E402
from teleop_rt.model import RobotModel  # noqa: E402


def pct(a: np.ndarray, p: float) -> float:
    return float(np.percentile(a, p)) if len(a) else float("nan")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "config",
        nargs="?",
        default=str(ROOT / "configs" / "can_emulated.yaml"),
        help="session config with a can: section (default: configs/can_emulated.yaml)",
    )
    p.add_argument(
        "--seconds", type=float, default=60.0, metavar="S",
        help="how long the loop runs against the emulator, in seconds of wall time (default 60)",
    )  # fmt: skip
    p.add_argument(
        "--side", choices=("hsi", "to"), default="hsi", help="the robot to run (default hsi)"
    )
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config value, for the master and the emulator (repeatable)",
    )  # fmt: skip
    p.add_argument("--emulator-realtime", action="store_true", help="SCHED_FIFO for the emulator")
    p.add_argument(
        "--emulator-poll-us", type=float, default=None, metavar="US",
        help="the emulator's --poll-us (its default if not given; 0: it blocks on the bus)",
    )  # fmt: skip
    p.add_argument(
        "--transport-free-cycles", type=int, default=20000, metavar="N",
        help="cycles of the backend's own CPU measured without a transport (default 20000)",
    )  # fmt: skip
    args = p.parse_args(argv)
    overrides = [*args.overrides, "can.emulate=false"]
    try:
        cfg = config.load(args.config, overrides)
    except TeleopError as exc:
        print(f"bench_can: error: {exc}", file=sys.stderr)
        return 2
    cmd = [
        sys.executable,
        str(ROOT / "tools" / "drive_emulator.py"),
        args.config,
        "--side",
        args.side,
    ]
    for o in overrides:
        cmd += ["--set", o]
    if args.emulator_realtime:
        cmd.append("--realtime")
    if args.emulator_poll_us is not None:
        cmd += ["--poll-us", str(args.emulator_poll_us)]
    emulator = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    try:
        for line in emulator.stdout:
            print(f"[emulator] {line.rstrip()}")
            if line.startswith("ready"):
                break
        else:
            print("bench_can: error: the emulator did not start", file=sys.stderr)
            return 1
        code = run(cfg, args)
    finally:
        emulator.terminate()
        try:
            out, _ = emulator.communicate(timeout=5)
            for line in out.splitlines():
                print(f"[emulator] {line}")
        except subprocess.TimeoutExpired:
            emulator.kill()
    if code == 0 and args.transport_free_cycles:  # a run that failed is reported as such
        transport_free(cfg, args.side, args.transport_free_cycles)
    return code


def transport_free(cfg: config.SessionConfig, side: str, cycles: int) -> None:
    """The backend's read + write against a bus that answers every SYNC at once."""
    from collections import deque

    import can

    from teleop_rt.hal.can import codec
    from teleop_rt.hal.can.startup import DriveInfo

    class PrimedBus(can.BusABC):
        def __init__(self, frames: list[can.Message]) -> None:
            super().__init__(channel="primed")
            self.frames, self.queue = frames, deque()

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            if msg.arbitration_id == codec.COB_ID_SYNC:
                self.queue.extend(self.frames)

        def _recv_internal(self, timeout: float | None):
            return (self.queue.popleft() if self.queue else None), True

    model = RobotModel.from_spec(getattr(cfg, side).robot, side)
    backend = create_backend("can", cfg, side, model)
    units = codec.JointUnits(4096, 20, 0.05, 1, "counts_per_s")
    info = [DriveInfo(n, 0, 0, 50, units) for n in backend.node_ids]
    frames = []
    for node in backend.node_ids:
        frames.append(can.Message(arbitration_id=0x180 + node, data=bytes(8), is_extended_id=False))
        frames.append(
            can.Message(arbitration_id=0x280 + node, data=b"\x37\x02\0\0", is_extended_id=False)
        )
    if backend.sensor is not None:
        size = backend._sensor_layout.size
        frames.append(can.Message(arbitration_id=backend.sensor.cob_id, data=bytes(size)))
    backend.spec = backend.spec.model_copy(update={"emulate": True})  # no pacing
    backend.window_ns = 0
    backend.hb_timeout_ns = 1 << 62  # no heartbeats on this bus
    backend.configure_started(info, PrimedBus(frames))
    backend.activate()
    tau = [0.0] * backend.n
    cpu = np.zeros(cycles, dtype=np.int64)
    thread_ns = time.thread_time_ns
    for k in range(cycles):
        c0 = thread_ns()
        backend.read()
        backend.write(tau)
        cpu[k] = thread_ns() - c0
    backend.shutdown()
    cpu = cpu / 1e3
    print(f"\nthe backend alone (no transport, {len(frames)} frames in per cycle, {cycles} cycles):"
          f" CPU per cycle p50 {pct(cpu, 50):.0f} us, p99 {pct(cpu, 99):.0f} us")  # fmt: skip


def run(cfg: config.SessionConfig, args: argparse.Namespace) -> int:
    side = args.side
    model = RobotModel.from_spec(getattr(cfg, side).robot, side)
    backend = create_backend("can", cfg, side, model)
    n_ticks = round(args.seconds * cfg.rate_hz)
    cpu = np.zeros(n_ticks, dtype=np.int64)
    wall = np.zeros(n_ticks, dtype=np.int64)
    late = np.zeros(n_ticks, dtype=np.int64)
    clock = TickClock(round(cfg.dt * 1e9), realtime=True, overrun="catch_up")
    tau = [0.0] * backend.n
    # as a session does: the grant first, so that the start-up's cyclic part (sensor zeroing,
    # enabling) already runs at the loop's priority and on its CPU
    grant = acquire_realtime()
    print("; ".join(grant.notes))
    t0 = time.perf_counter()
    try:
        backend.configure()
        backend.activate()
    except TeleopError as exc:  # a safety stop or a drive that does not answer
        backend.shutdown()
        grant.release()
        print(f"bench_can: error: start-up failed: {exc}", file=sys.stderr)
        return 3
    print(f"start-up (reset, SDO, NMT, sensor zeroing, enable): {time.perf_counter() - t0:.2f} s")
    base = dict(backend.stats)
    done, stop_reason, missed_deadlines = 0, None, 0
    thread_ns, perf_ns = time.thread_time_ns, time.perf_counter_ns
    try:
        clock.start()
        for k in range(n_ticks):
            late[k] = clock.wait()
            c0, w0 = thread_ns(), perf_ns()
            fb = backend.read()
            v = fb.v
            for j in range(backend.n):
                tau[j] = -0.05 * v[j]
            backend.write(tau)
            c1, w1 = thread_ns(), perf_ns()
            cpu[k], wall[k] = c1 - c0, w1 - w0
            missed_deadlines += clock.finish(clock.now_ns())
            done = k + 1
    except SafetyStop as exc:
        stop_reason = str(exc)
    finally:
        backend.shutdown()  # as a session does: the drives safe first, then the grant
        grant.release()
    cpu, wall, late = cpu[:done] / 1e3, wall[:done] / 1e3, late[:done] / 1e3
    stats = {k: backend.stats[k] - base[k] for k in base}
    print(f"\n{done} cycles of {n_ticks} at {cfg.rate_hz} Hz ({side}: {backend.n} drives"
          f"{' + torque sensor' if backend.sensor else ''}, {os.cpu_count()} CPUs)")  # fmt: skip
    if stop_reason:
        print(f"stopped early: {stop_reason}")
    window = cfg.can.feedback_window_us
    print(f"missed feedback windows: {stats['missed_windows']} (window {window} us after SYNC); "
          f"late frames: {stats['late_frames']}")  # fmt: skip
    if stats["bus_warnings"]:
        print(f"warning error frames (not faults): {stats['bus_warnings']}, "
              f"the last: {backend.last_bus_warning}")  # fmt: skip
    worst = cpu.max() if done else float("nan")
    print(f"master CPU per cycle (read + write): p50 {pct(cpu, 50):.0f} us, "
          f"p99 {pct(cpu, 99):.0f} us, max {worst:.0f} us")  # fmt: skip
    print(f"wall time per cycle (incl. waiting for the drives): p50 {pct(wall, 50):.0f} us, "
          f"p99 {pct(wall, 99):.0f} us")  # fmt: skip
    print(f"deadline lateness: p50 {pct(late, 50):.0f} us, p99 {pct(late, 99):.0f} us; "
          f"missed deadlines: {missed_deadlines}")  # fmt: skip
    return 0 if stop_reason is None else 3


if __name__ == "__main__":
    sys.exit(main())
