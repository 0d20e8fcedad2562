#!/usr/bin/env python3
"""CiA 402 drive emulator: plays a session's CAN drives (and torque sensors) in a process of its
own, so that ``teleop-rt run CONFIG --backend can`` closes the same physical loop as the sim
backend over a real python-can interface.

    python tools/drive_emulator.py CONFIG [--side hsi|to|both] [--set key=value ...]
        [--sensor-offset NM] [--fault KIND:NODE@TICK[+TICKS] ...] [--duration S]
        [--realtime] [--poll-us US]

The buses, node ids and units come from the config's ``can:`` section (its defaults when the
config has none: udp_multicast 239.74.163.1 port 43113 for the HSI, 239.74.163.2 port 43114 for
the TO, hop_limit 0 so no frame leaves this host, nodes 1 and 2, sensor TPDO 0x18A), the joint
dynamics, operator and environment from
the rest of the config: the project's simulated plant, advanced one period per SYNC. Every
robot (``--side both``, the default) is served by a process of its own.

Each emulated drive is a canopen LocalNode (SDO server, NMT, heartbeat, EMCY) with the CiA 402
state machine and the SYNC / PDO exchange of ``teleop_rt.hal.can.emulator``. An NMT reset node
from the master (the backend sends one at start) puts the robot back at its initial pose, so
several runs can use one emulator.

Fault injection (repeatable), KIND one of drop_tpdo, emcy, stop_heartbeat, status_fault,
error_frame, drop_sensor, long_tpdo; NODE a node id or '*' (every drive); TICK counted from
the moment the robot's drives are all enabled (the session's tick 0, within a tick or two);
+TICKS a duration:

    --fault emcy:2@3000  --fault drop_tpdo:1@5000+2  --fault stop_heartbeat:*@4000

A fault without a side prefix applies to every emulated robot: ``--fault to:emcy:2@3000``
affects the TO only.
"""

from __future__ import annotations

import argparse
import re
import signal
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.errors import TeleopError  # noqa: E402
from teleop_rt.hal.can.config import CanSpec  # noqa: E402

CHILD_EXIT_S = 5.0  # --side both: an emulator asked to end is killed after this long
_FAULT = re.compile(r"^(?:(hsi|to):)?([a-z_]+):(\d+|\*)@(\d+)(?:\+(\d+))?$")


def parse_fault(text: str):
    """'[side:]kind:node@tick[+ticks]' -> (side or None, Fault)."""
    from teleop_rt.hal.can.emulator import Fault

    m = _FAULT.match(text)
    if not m:
        raise argparse.ArgumentTypeError(
            f"--fault {text!r}: expected [side:]KIND:NODE@TICK[+TICKS], e.g. emcy:2@3000"
        )
    side, kind, node, tick, ticks = m.groups()
    try:
        fault = Fault(
            kind, None if node == "*" else int(node), int(tick), int(ticks) if ticks else None
        )
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--fault {text!r}: {exc}") from None
    return side, fault


def fault_text(side: str | None, fault) -> str:
    """The --fault argument that gave ``fault`` (for messages)."""
    node = "*" if fault.node_id is None else fault.node_id
    ticks = "" if fault.ticks is None else f"+{fault.ticks}"
    return f"{side + ':' if side else ''}{fault.kind}:{node}@{fault.at_tick}{ticks}"


def check_faults(faults: list, spec: CanSpec, sides: tuple[str, ...]) -> str | None:
    """What is wrong with the first fault naming a drive node that a robot it applies to (of
    ``sides``, the ones emulated here) does not have; None if nothing is."""
    for side, fault in faults:
        for s in sides if side is None else [side] if side in sides else []:
            nodes = [d.node_id for d in spec.side(s).drives]
            if fault.node_id is not None and fault.node_id not in nodes:
                return (
                    f"--fault {fault_text(side, fault)}: the {s} robot has no drive node "
                    f"{fault.node_id} (its nodes: {', '.join(map(str, nodes))})"
                )
    return None


def main(argv: list[str] | None = None) -> int:
    from teleop_rt.hal.can.emulator import FAULT_KINDS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="session config (YAML)")
    p.add_argument(
        "--side", choices=("hsi", "to", "both"), default="both",
        help="whose drives to emulate: the HSI's, the TO's, or both robots' (default; one "
        "process per robot)",
    )  # fmt: skip
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config key, as for teleop-rt run (repeatable)",
    )  # fmt: skip
    p.add_argument(
        "--sensor-offset", type=float, default=0.0, metavar="NM",
        help="constant bias of the emulated torque sensors (the master zeroes it at start-up)",
    )  # fmt: skip
    p.add_argument(
        "--fault", type=parse_fault, action="append", default=[],
        metavar="[SIDE:]KIND:NODE@TICK[+TICKS]",
        help=f"inject a fault (repeatable): KIND one of {', '.join(FAULT_KINDS)}; NODE a drive's "
        "node id or '*' (every drive); TICK counted from the moment the robot's drives are all "
        "enabled; +TICKS how long it lasts (default: for good); SIDE hsi or to (default: every "
        "emulated robot); e.g. to:emcy:2@3000",
    )  # fmt: skip
    p.add_argument("--duration", type=float, default=None, metavar="S", help="then exit")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument(
        "--realtime", action="store_true",
        help="ask for SCHED_FIFO and freeze the garbage collector (a drive answers in time)",
    )  # fmt: skip
    p.add_argument(
        "--poll-us", type=float, default=100.0, metavar="US",
        help="poll the bus, sleeping US between empty polls (default 100; 0 blocks on the bus "
        "instead): on this project's VM polling answered SYNC late 10-40x less often, for "
        "about 10 %% of a CPU while no frame comes",
    )  # fmt: skip
    args = p.parse_args(argv)
    if args.poll_us < 0:
        p.error(f"--poll-us must be >= 0, got {args.poll_us:g}")
    try:
        cfg = config.load(args.config, args.overrides)
    except TeleopError as exc:
        print(f"drive_emulator: error: {exc}", file=sys.stderr)
        return 2

    import can

    from teleop_rt.hal.can.emulator import DriveEmulator

    spec = cfg.can or CanSpec()
    sides = ("hsi", "to") if args.side == "both" else (args.side,)
    problem = check_faults(args.fault, spec, sides)
    if problem is not None:
        print(f"drive_emulator: error: {problem}", file=sys.stderr)
        return 2
    if args.side == "both":  # one process per robot: a drive must not wait for the GIL
        return _both(argv if argv is not None else sys.argv[1:])
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):  # at any moment from here: a clean end
        signal.signal(signum, lambda *_: stop.set())
    emulators, threads, buses = [], [], []  # one side per process (see _both)
    for side in sides:
        kwargs = spec.side(side).bus.kwargs()
        try:
            bus = can.Bus(**kwargs)
        except (can.CanError, ImportError, OSError, ValueError) as exc:
            print(f"drive_emulator: error: {side} bus {kwargs}: {exc}", file=sys.stderr)
            return 1
        buses.append(bus)
        try:
            emu = DriveEmulator(bus, cfg, side, sensor_offset_nm=args.sensor_offset)
        except TeleopError as exc:
            print(f"drive_emulator: error: {exc}", file=sys.stderr)
            bus.shutdown()
            return 2
        for fault_side, fault in args.fault:
            if fault_side in (None, side):
                emu.inject(fault)
        emulators.append(emu)
        threads.append(
            threading.Thread(
                target=emu.serve, args=(stop, 5, args.poll_us / 1e6), name=f"emulator-{side}"
            )
        )
        if not args.quiet:
            nodes = ", ".join(str(d.node_id) for d in emu.drives)
            sensor = spec.side(side).torque_sensor
            extra = f", torque sensor TPDO 0x{sensor.cob_id:03X}" if sensor else ""
            where = " ".join(str(kwargs[k]) for k in ("interface", "channel") if k in kwargs)
            print(f"emulating {side}: drives {nodes}{extra} on {where}", flush=True)

    if args.realtime:
        from teleop_rt.loop import acquire_realtime

        # CPU 0: the control loop pins itself to the last CPU
        notes = acquire_realtime(priority=70, cpu=0).notes
        if not args.quiet:
            print("; ".join(notes), flush=True)
    for t in threads:
        t.start()
    if not args.quiet:
        print("ready (Ctrl-C stops)", flush=True)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
        stop.wait(0.2)
    stop.set()
    for t in threads:
        t.join(2.0)
    for bus in buses:
        bus.shutdown()
    if not args.quiet:
        for side, emu in zip(sides, emulators, strict=True):
            states = ", ".join(f"node {d.node_id}: {d.state}" for d in emu.drives)
            print(f"{side}: {emu.sync_count} SYNCs, world tick {emu.world_tick}; {states}")
    return 0


def _both(argv: list[str]) -> int:
    """Run this tool once per robot, in two processes, until both have ended. SIGINT (Ctrl-C,
    or ``kill -INT`` of this process alone) and SIGTERM end both, as does one of them failing;
    an emulator that does not end within CHILD_EXIT_S of being asked is killed."""
    import subprocess

    rest, skip = [], False
    for a in argv:  # drop '--side X' / '--side=X'
        if skip:
            skip = False
        elif a == "--side":
            skip = True
        elif not a.startswith("--side="):
            rest.append(a)
    children = [
        subprocess.Popen(
            [sys.executable, __file__, *rest, "--side", side], stdin=subprocess.DEVNULL
        )
        for side in ("hsi", "to")
    ]
    asked: list[float] = []  # when the children were asked to end

    def end(*_) -> None:
        # SIGTERM, not SIGINT: an emulator takes it at any moment (a second Ctrl-C during its
        # own shutdown would be a traceback); after a terminal's Ctrl-C they have both anyway
        if not asked:
            asked.append(time.monotonic())
        for c in children:
            if c.poll() is None:
                c.terminate()

    signal.signal(signal.SIGINT, end)
    signal.signal(signal.SIGTERM, end)
    while (codes := [c.poll() for c in children]).count(None):
        if not asked and any(code not in (None, 0) for code in codes):
            end()  # one failed: the other's robot alone is no use
        if asked and time.monotonic() - asked[0] > CHILD_EXIT_S:
            for c in children:
                if c.poll() is None:
                    c.kill()
        time.sleep(0.05)
    # an emulator ended by our signal ended as asked
    return max(0 if asked and code < 0 else code for code in codes)


if __name__ == "__main__":
    sys.exit(main())
