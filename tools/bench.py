#!/usr/bin/env python3
"""Benchmark of the 1 kHz loop: tick cost, recording cost, real-time lateness, scaling.

    python tools/bench.py [CONFIG] [--ticks N] [--repeat R] [--rt-seconds S] [--joints 2,4,8]
                          [--json OUT]

Prints, from one run on this machine (shared machines are noisy: compare figures of one run,
and read the medians, not the maxima):
1. what the OS grants a real-time loop (SCHED_FIFO, CPU affinity, mlockall, frozen GC);
2. the Pinocchio floor: the per-tick Pinocchio calls alone (2 RNEA, 2 ABA, 2 frame Jacobians);
3. the full simulated tick (both models, controllers, channel, both plants) without and with
   recording, the log writer process's CPU per tick (and its fixed start and close cost) and
   the log's bytes per tick, beside its floors (the SDK's log calls alone, a bare fork and
   exit of this process), and the controller-side tick (what runs against hardware: read,
   models, controllers, channel, safety, write; the feedback replayed from a simulated run);
4. real-time mode, S seconds at 1 kHz with recording on: deadline lateness percentiles and
   the ticks that started more than a whole period late, the writer's CPU and bytes per tick;
   then the host's own wake-up latency under the same grant for S seconds, measured by
   cyclictest (rt-tests) if it is installed;
5. what each channel kind costs: the full tick (recording off) at a 20 ms delay with the plain
   wave channel (zero reconstruction), the protected wave (bounded), TDPA, and the last two
   with the deadband codec (issue 24), alternated in one run, and the difference to the plain
   wave channel (issue 17's target: <= 2 us);
6. what the workspace mapping costs (teleop_rt.mapping): identity, joint scaling with a clutch
   script, the plane's per-site Jacobian map, alternated in one run;
7. how the tick grows with the number of joints (chains generated from one template), joint
   to joint and coupled in task space (planar chains in the plane, spatial ones in 3-D and in
   the pose): what the task-space map adds per site (issue 26's target: <= 2 us for 6
   joints), beside its Pinocchio floor (the map's frame Jacobian alone).
Times are min / median / p99 over R repeats of N ticks (the repeat with the lowest median).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.com.link import InProcessLink  # noqa: E402
from teleop_rt.errors import TeleopError  # noqa: E402
from teleop_rt.flat import Packed  # noqa: E402
from teleop_rt.hal.base import Backend, Feedback  # noqa: E402
from teleop_rt.hal.registry import register_backend  # noqa: E402
from teleop_rt.loop import acquire_realtime  # noqa: E402
from teleop_rt.recording.recorder import Recorder  # noqa: E402
from teleop_rt.session import Session  # noqa: E402

PAPER = ROOT / "configs/paper_experiment.yaml"


# --- measurement helpers ----------------------------------------------------------------------
def time_ticks(tick: Callable[[], None], ticks: int) -> np.ndarray:
    """Per-tick wall time (us) of ``ticks`` calls, garbage collector off."""
    out = np.zeros(ticks, dtype=np.int64)
    perf = time.perf_counter_ns
    gc.collect()
    gc.disable()
    try:
        for k in range(ticks):
            t0 = perf()
            tick()
            out[k] = perf() - t0
    finally:
        gc.enable()
    return out / 1e3


def best_of(runs: list[np.ndarray]) -> dict:
    """min / median / p99 of the repeat with the lowest median, and the spread of medians."""
    medians = [float(np.median(r)) for r in runs]
    best = runs[int(np.argmin(medians))]
    return {
        "min": float(best.min()),
        "median": float(np.median(best)),
        "p99": float(np.percentile(best, 99)),
        "medians_of_repeats": medians,
    }


def line(label: str, s: dict) -> str:
    reps = ", ".join(f"{m:.1f}" for m in s["medians_of_repeats"])
    return (
        f"  {label:<34} min {s['min']:6.1f}  median {s['median']:6.1f}  p99 {s['p99']:6.1f} us"
        f"   (medians: {reps})"
    )


# --- the controller side against replayed feedback -------------------------------------------
class ReplayedFeedback(Backend):
    """Feeds back the measurements of a simulated run, tick by tick: the session then does
    exactly what it does against hardware (the commands equal those of the simulated run, so
    the safety layer's tracking check holds), without a plant."""

    def __init__(self, samples: list[tuple[list[float], list[float], list[float]]]) -> None:
        super().__init__(len(samples[0][0]))
        # each tick's q, v, tau_ext as float64 memoryviews: read copies them as a driver's
        # decoded frames would be copied (three memcpys), not through numpy calls
        self.samples = [tuple(memoryview(np.array(x, dtype=float)) for x in s) for s in samples]
        self.k = 0

    def read(self) -> Feedback:
        fb = self.feedback
        q, v, tau = self.samples[self.k]
        fb.q_mv[:] = q
        fb.v_mv[:] = v
        fb.tau_mv[:] = tau
        return fb

    def write(self, tau: list[float]) -> None:
        self.k += 1


def record_feedback(cfg, ticks: int) -> dict[str, list]:
    session = Session(cfg)
    samples: dict[str, list] = {"hsi": [], "to": []}
    for _ in range(ticks):
        session.step()
        for side in (session.hsi, session.to):
            fb = side.backend.feedback
            samples[side.name].append((list(fb.q), list(fb.v), list(fb.tau_ext)))
    return samples


def replayed_session(cfg, samples: dict[str, list]) -> Session:
    """A session whose backends replay recorded feedback (registered as backend 'replayed')."""

    def make(cfg, side: str, model, operator=None) -> ReplayedFeedback:
        return ReplayedFeedback(samples[side])

    register_backend("replayed")(make)
    return Session(cfg.model_copy(update={"backend": "replayed"}))


def controller_side(cfg, samples: dict[str, list], ticks: int) -> np.ndarray:
    return time_ticks(replayed_session(cfg, samples).step, ticks)


def each_site_alone(cfg, samples: dict[str, list], ticks: int) -> dict[str, np.ndarray]:
    """Each site's controller-side tick on buffers of its own, as a site in a process of its
    own runs it (sense, the link, update; its backend replays recorded feedback): both sites
    over a Python InProcessLink, each timed around its own calls."""
    session = replayed_session(cfg, samples)
    hsi, to = session.sites
    for site in (hsi, to):
        site.bind(Packed(site.blocks))
    link = InProcessLink(session.n, cfg.delay_ticks)
    t_h, t_t = np.zeros(ticks, dtype=np.int64), np.zeros(ticks, dtype=np.int64)
    perf = time.perf_counter_ns
    gc.collect()
    gc.disable()
    try:
        for k in range(ticks):
            t0 = perf()
            hsi.sense(link)
            t1 = perf()
            to.sense(link)
            t2 = perf()
            hsi.update(link)
            t3 = perf()
            to.update(link)
            t4 = perf()
            t_h[k], t_t[k] = (t1 - t0) + (t3 - t2), (t2 - t1) + (t4 - t3)
    finally:
        gc.enable()
    return {"hsi": t_h / 1e3, "to": t_t / 1e3}


# --- sections --------------------------------------------------------------------------------
def grant() -> list[str]:
    g = acquire_realtime()
    g.release()
    return g.notes


def pinocchio_floor(cfg) -> dict:
    """The Pinocchio calls of one tick, alone (both robots: RNEA, ABA, frame Jacobian)."""
    session = Session(cfg)
    calls = []
    for side in (session.hsi, session.to):
        m = side.model
        q, v, a = side.feedback.q, side.feedback.v, np.zeros(m.nv)
        calls += [
            lambda m=m, q=q, v=v, a=a: pin.rnea(m.model, m.data, q, v, a),
            lambda m=m, q=q, v=v, a=a: pin.aba(m.model, m.data, q, v, a),
            lambda m=m, q=q: pin.computeFrameJacobian(
                m.model, m.data, q, m.ee_frame_id, pin.LOCAL_WORLD_ALIGNED
            ),
        ]

    def tick() -> None:
        for c in calls:
            c()

    return best_of([time_ticks(tick, 5000) for _ in range(3)])


def full_tick(cfg, ticks: int, repeat: int, tmp: Path) -> dict:
    """Without and with recording, alternating (the recorded tick includes the hot-path
    ``record`` call; its writer process runs beside it, on the other core if there is one).
    The writer's CPU per tick counts its whole life (start and close too), and a writer started
    and closed without a tick, once per repeat, gives that fixed part alone."""
    plain, logged, writer_us, log_bytes, fixed_ms = [], [], [], [], []
    for r in range(repeat):
        plain.append(time_ticks(Session(cfg).step, ticks))
        session = Session(cfg)
        cpu_before = children_cpu_s()
        path = tmp / f"bench-{r}.mcap"
        recorder = Recorder(session, path)
        step, record = session.step, recorder.record

        def tick(step=step, record=record) -> None:
            step()
            record(0, 0, False)

        try:
            logged.append(time_ticks(tick, ticks))
        finally:
            recorder.close(None)
        published = max(recorder.published, 1)
        writer_us.append(1e6 * (children_cpu_s() - cpu_before) / published)
        log_bytes.append(path.stat().st_size / published)
        cpu_before = children_cpu_s()
        Recorder(Session(cfg), tmp / f"bench-empty-{r}.mcap").close(None)
        fixed_ms.append(1e3 * (children_cpu_s() - cpu_before))
    beyond = [us - 1e3 * ms / ticks for us, ms in zip(writer_us, fixed_ms, strict=True)]
    topics = [t.name for t in recorder.layout.topics]
    return {"plain": best_of(plain), "recorded": best_of(logged), "writer_cpu_us": writer_us,
            "writer_fixed_ms": fixed_ms, "writer_per_tick_us": beyond,
            "log_bytes_per_tick": log_bytes,
            "floors": writer_floors(path, topics, tmp)}  # fmt: skip


def writer_floors(log: Path, topics: list[str], tmp: Path, repeat: int = 5) -> dict:
    """The log writer's floors, measured in this process: the SDK's log call alone per tick
    (the messages of ``topics`` in ``log``, re-logged from a ready list with the writer's MCAP
    options: while each topic's tick is one message, the writer's per-tick part cannot go
    below it), and a bare fork and exit of this process (what the kernel takes to copy and
    tear down the address space a forked writer inherits: the floor of its fixed part).
    Minimum of ``repeat``."""
    import foxglove
    from mcap.reader import make_reader

    from teleop_rt.recording.writer import write_options

    with open(log, "rb") as f:
        found = make_reader(f).iter_messages(topics=topics, log_time_order=False)
        messages = [(ch.topic, message.data, message.log_time) for _, ch, message in found]
    sdk_us = []
    for r in range(repeat):
        context = foxglove.Context()
        out = tmp / f"floor-{r}.mcap"
        writer = foxglove.open_mcap(str(out), context=context, writer_options=write_options())
        schema = foxglove.Schema(name="floor", encoding="ros2msg", data=b"uint8[] data")
        logs = {t: foxglove.Channel(t, message_encoding="cdr", schema=schema,
                                    context=context).base.log for t in topics}  # fmt: skip
        calls = [(logs[t], data, stamp) for t, data, stamp in messages]
        t0 = time.process_time_ns()
        for log, data, stamp in calls:
            log(data, stamp)
        sdk_us.append((time.process_time_ns() - t0) / 1e3 / (len(calls) / len(topics)))
        writer.close()
    chunk_us = [_chunk_floor(messages, topics) for _ in range(repeat)]
    fork_ms = []
    for _ in range(repeat):
        pid = os.fork()
        if pid == 0:
            os._exit(0)
        usage = os.wait4(pid, 0)[2]
        fork_ms.append(1e3 * (usage.ru_utime + usage.ru_stime))
    return {"sdk_log_us_per_tick": min(sdk_us), "messages_per_tick": len(topics),
            "chunks_us_per_tick": min(chunk_us), "fork_exit_ms": min(fork_ms)}  # fmt: skip


def _chunk_floor(messages: list[tuple[str, bytes, int]], topics: list[str]) -> float:
    """CPU per tick of the writer's own chunks for the same ready payloads: message records
    built per batch of 1 024 ticks (``TickRecords``), LZ4, CRCs and message indexes, into an
    MCAP file on /dev/null (``McapFile``)."""
    from teleop_rt.recording.chunks import TickRecords
    from teleop_rt.recording.mcap_file import McapFile

    per_topic = {t: [(d[4:], s) for topic, d, s in messages if topic == t] for t in topics}
    ticks = min(len(v) for v in per_topic.values())
    payloads = [np.frombuffer(b"".join(d for d, _ in per_topic[t][:ticks]), np.uint8)
                .reshape(ticks, -1) for t in topics]  # fmt: skip
    stamps = np.array([s for _, s in per_topic[topics[0]][:ticks]], np.int64)
    fd = os.open(os.devnull, os.O_WRONLY)
    try:
        t0 = time.process_time_ns()
        file = McapFile(fd, "ros2", "bench", lambda errno: None)
        ids = [file.channel(t, "cdr", (t, "ros2msg", b"uint8[] data\n")) for t in topics]
        records = TickRecords(file, ids, [p.shape[1] for p in payloads], prefix=b"\0\1\0\0")
        for lo in range(0, ticks, 1024):
            records.add([p[lo : lo + 1024] for p in payloads], stamps[lo : lo + 1024])
        records.flush()
        file.close()
        return (time.process_time_ns() - t0) / 1e3 / ticks
    finally:
        os.close(fd)


CHANNEL_KINDS = {  # label -> overrides; the first is the baseline
    "plain wave (zero)": ["channel.mode=wave", "channel.wave_reconstruction=zero"],
    "protected wave (bounded)": ["channel.mode=wave", "channel.wave_reconstruction=bounded"],
    "drift-corrected wave (corrected)": ["channel.mode=wave",
                                         "channel.wave_reconstruction=corrected"],
    "energy-reflecting wave (reflected)": ["channel.mode=wave",
                                           "channel.wave_reconstruction=reflected"],
    "TDPA": ["channel.mode=tdpa"],
    "protected wave + deadband codec": ["channel.mode=wave", "channel.codec=deadband"],
    "TDPA + deadband codec": ["channel.mode=tdpa", "channel.codec=deadband"],
}


def channel_kinds(path: Path, ticks: int, repeat: int) -> dict[str, dict]:
    """The full tick per channel kind at a 20 ms delay, the kinds alternated in each repeat."""
    runs: dict[str, list[np.ndarray]] = {label: [] for label in CHANNEL_KINDS}
    for _ in range(repeat):
        for label, overrides in CHANNEL_KINDS.items():
            cfg = config.load(path, ["channel.delay_ms=20", *overrides])
            runs[label].append(time_ticks(Session(cfg).step, ticks))
    return {label: best_of(r) for label, r in runs.items()}


MAPPINGS = {  # label -> overrides (teleop_rt.mapping); the first is the baseline
    "joint, identity": [],
    "joint, scaled + clutch": [
        "mapping.motion_scale=0.2",
        "mapping.force_scale=5",
        "operator.clutch=[{start_s: 1000, end_s: 1001}]",
    ],  # fmt: skip
    "plane (J, J# per site)": ["channel.space=plane", "channel.wave_impedance=50"],
}


def mappings(path: Path, ticks: int, repeat: int) -> dict[str, dict]:
    """The full tick per mapping at a 20 ms delay, alternated in each repeat."""
    runs: dict[str, list[np.ndarray]] = {label: [] for label in MAPPINGS}
    for _ in range(repeat):
        for label, overrides in MAPPINGS.items():
            cfg = config.load(path, ["channel.delay_ms=20", *overrides])
            runs[label].append(time_ticks(Session(cfg).step, ticks))
    return {label: best_of(r) for label, r in runs.items()}


def children_cpu_s() -> float:
    """CPU time (user + system) of this process's finished children: the log writers."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def realtime(cfg, seconds: float, tmp: Path) -> dict:
    session = Session(cfg)
    cpu_before = children_cpu_s()
    path = tmp / "bench-rt.mcap"
    recorder = Recorder(session, path)
    summary = session.run(ticks=int(seconds * cfg.rate_hz), realtime=True, recorder=recorder)
    published = max(recorder.published, 1)
    return {"timing": summary.timing, "notes": summary.notes, "stopped": summary.stopped_early,
            "writer_cpu_us": 1e6 * (children_cpu_s() - cpu_before) / published,
            "log_bytes_per_tick": path.stat().st_size / published}  # fmt: skip


def host_baseline(seconds: float, rate_hz: float, priority: int = 80) -> dict | None:
    """The host's own wake-up latency under the loop's grant (SCHED_FIFO, the same CPU, locked
    memory, wake-up latency held at 0 us: cyclictest's defaults), measured by rt-tests'
    cyclictest, the field's standard tool: a C thread that does nothing but sleep to absolute
    deadlines. What it sees late, no loop on this host can be on
    time for. None if cyclictest is not installed."""
    exe = shutil.which("cyclictest")
    if exe is None:
        return None
    period_us = round(1e6 / rate_hz)
    cpu = sorted(os.sched_getaffinity(0))[-1]  # where acquire_realtime pins the loop
    loops, bins = int(seconds * rate_hz), 3 * period_us
    cmd = [exe, "-q", "-m", "-t", "1", "-p", str(priority), "-a", str(cpu),
           "-i", str(period_us), "-l", str(loops), "-h", str(bins)]  # fmt: skip
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=2 * seconds + 60)
        if done.returncode != 0:
            lines = done.stderr.strip().splitlines() or [f"exit {done.returncode}"]
            return {"error": "; ".join(lines)}
        return cyclictest_summary(done.stdout, period_us)
    except (subprocess.TimeoutExpired, OSError, ValueError) as err:  # the rest of the bench goes on
        return {"error": str(err)}


def cyclictest_summary(text: str, period_us: int) -> dict:
    """p50 / p99 / p99.9 / max (us) and the wake-ups later than a whole period, from
    cyclictest's histogram output (one thread; 1 us bins, overflows beyond the last bin)."""
    hist: dict[int, int] = {}
    overflows, max_us = 0, 0
    for row in text.splitlines():
        if row.startswith("# Histogram Overflows:"):
            overflows = int(row.split(":")[1].split()[0])
        elif row.startswith("# Max Latencies:"):
            max_us = int(row.split(":")[1].split()[0])
        elif row[:1].isdigit():
            latency, count = row.split()[:2]
            hist[int(latency)] = int(count)
    total = sum(hist.values()) + overflows
    if not total:
        raise ValueError("cyclictest printed no histogram")

    def percentile(p: float) -> float:
        seen = 0
        for latency in sorted(hist):
            seen += hist[latency]
            if seen >= p * total:
                return float(latency)
        return float(max_us)  # in the overflows

    # bin b holds [b, b + 1) us: from bin period_us on, later than a whole period
    late = overflows + sum(c for latency, c in hist.items() if latency >= period_us)
    return {
        "wakeups": total,
        "p50": percentile(0.5),
        "p99": percentile(0.99),
        "p99.9": percentile(0.999),
        "max": float(max_us),
        "late_over_period": late,
    }


SPATIAL_AXES = ("0 0 1", "0 1 0", "1 0 0")  # a spatial chain's joint axes, in turn


def chain_urdf(n: int, spatial: bool = False) -> str:
    """A serial chain of n revolute joints, 0.6 m long in all, a tool at its end: planar (z
    axes) or ``spatial`` (axes z, y, x in turn: the tool moves and turns in 3-D)."""
    length, mass = 0.6 / n, 2.0 / n
    inertia = mass * length * length / 12.0
    ixx = inertia if spatial else 1e-5
    parts = ['<robot name="chain">', '<link name="base"/>']
    parent = "base"
    for i in range(n):
        offset = 0.0 if i == 0 else length
        axis = SPATIAL_AXES[i % 3] if spatial else "0 0 1"
        parts += [
            f'<link name="l{i}"><inertial><origin xyz="{length / 2} 0 0"/><mass value="{mass}"/>'
            f'<inertia ixx="{ixx}" iyy="{inertia}" izz="{inertia}" ixy="0" ixz="0" iyz="0"/>'
            "</inertial></link>",
            f'<joint name="j{i}" type="revolute"><parent link="{parent}"/><child link="l{i}"/>'
            f'<origin xyz="{offset} 0 0"/><axis xyz="{axis}"/>'
            '<limit lower="-3" upper="3" velocity="20" effort="100"/>'
            '<dynamics damping="0.01" friction="0.0"/></joint>',
        ]
        parent = f"l{i}"
    parts += [
        '<link name="tool"/>',
        f'<joint name="tool_joint" type="fixed"><parent link="{parent}"/><child link="tool"/>'
        f'<origin xyz="{length} 0 0"/></joint>',
        "</robot>",
    ]
    return "\n".join(parts)


def chain_config(n: int, tmp: Path, spatial: bool = False) -> Path:
    """The paper experiment's structure on an n-joint chain (``spatial``: in 3-D): a hand
    moving the tool 2 cm, a wall out of reach (evaluated every tick, never touched)."""
    import yaml

    name = f"chain{n}{'s' if spatial else ''}"
    urdf = tmp / f"{name}.urdf"
    urdf.write_text(chain_urdf(n, spatial))
    q0 = [0.3] * n
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    pin.framesForwardKinematics(model, data, np.array(q0))
    x, y, z = data.oMf[model.getFrameId("tool")].translation.tolist()
    hand, wall = ([x + 0.02, y, z], [5.0, 0.0, 0.0]) if spatial else ([x + 0.02, y], [5.0, 0.0])
    normal = [-1, 0, 0] if spatial else [-1, 0]

    def side(kp: float) -> dict:  # a fresh dict per robot: no YAML aliases in the dump
        robot = {"urdf": urdf.name, "ee_frame": "tool", "q0_rad": list(q0)}
        return {"robot": robot, "virtual_mass": 0.1, "controller": {"kind": "p", "kp": kp}}

    spec = {
        "name": f"chain{n}",
        "duration_s": 10.0,
        "hsi": side(2.0),
        "to": side(20.0),
        "channel": {"mode": "wave", "delay_ms": 0, "wave_impedance": 2.0},
        "operator": {"kind": "hand", "waypoints": [{"t_s": 5.0, "position_m": hand}]},
        "environment": [
            {"kind": "wall", "point_m": wall, "normal": normal, "stiffness_n_per_m": 5000}
        ],
    }
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


PLANE = ["channel.space=plane", "channel.wave_impedance=50"]  # the task-space map (b in N s/m)


TASK_SPACES = {  # label -> (spatial chain, overrides); "joint" / "joint 3-D": the baselines
    "joint": (False, []),
    "plane": (False, PLANE),
    "joint 3-D": (True, []),
    "position": (True, ["channel.space=position", "channel.wave_impedance=50"]),
    "pose": (True, ["channel.space=pose", "channel.wave_impedance=[50,50,50,2,2,2]"]),
}
TASK_SPAN = {"position": 3, "pose": 6}  # the joints a spatial chain needs to span the task
MAP_GOAL_US = 2.0  # issue 26: the task-space map adds at most this per site at 6 joints


def map_floor(n: int, tmp: Path, spatial: bool) -> dict:
    """The map's own Pinocchio call, alone: one frame Jacobian (world-aligned) of the chain
    at its start pose (``chain_config`` wrote its URDF)."""
    model = pin.buildModelFromUrdf(str(tmp / f"chain{n}{'s' if spatial else ''}.urdf"))
    data, frame, q = model.createData(), model.getFrameId("tool"), np.full(n, 0.3)
    call, lwa = pin.computeFrameJacobian, pin.LOCAL_WORLD_ALIGNED
    return best_of([time_ticks(lambda: call(model, data, q, frame, lwa), 5000) for _ in range(3)])


def scaling(joints: list[int], ticks: int, repeat: int, tmp: Path) -> list[dict]:
    """Full tick per joint count, joint to joint and coupled in task space (each site's
    Jacobian map, ``teleop_rt.mapping``): planar chains in the plane, spatial chains (with
    their own joint-to-joint baseline) in 3-D and in the pose where they span it; the repeats
    go round the joint counts and the maps, so a change of the machine's speed during the run
    hits every one alike. Each row also has the map's Pinocchio floor (one frame Jacobian)."""
    configs = {}
    for n in joints:
        for label, (spatial, overrides) in TASK_SPACES.items():
            if n >= TASK_SPAN.get(label, 0) and (not spatial or n >= 3):
                configs[n, label] = config.load(chain_config(n, tmp, spatial), overrides)
    runs: dict[tuple[int, str], list[np.ndarray]] = {key: [] for key in configs}
    for _ in range(repeat):
        for key, cfg in configs.items():
            runs[key].append(time_ticks(Session(cfg).step, ticks))
    rows = []
    for n in joints:
        row = {"joints": n, **best_of(runs[n, "joint"])}
        for label in TASK_SPACES:
            if label != "joint" and (n, label) in runs:
                row[label] = best_of(runs[n, label])
        row["map_floor"] = map_floor(n, tmp, n >= 3)
        rows.append(row)
    return rows


def map_cost(row: dict, label: str) -> float | None:
    """What the task-space map adds per site (us, medians): against the chain's own joint
    baseline, both sites' difference halved (None: not run at this joint count)."""
    if label not in row:
        return None
    base = row["joint 3-D"] if TASK_SPACES[label][0] else row
    return (row[label]["median"] - base["median"]) / 2


def main() -> int:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "config", nargs="?", default=str(PAPER), help="session config (default: the paper's)"
    )
    parser.add_argument(
        "--ticks", type=int, default=10_000, metavar="N", help="ticks per repeat (default 10000)"
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=3,
        metavar="R",
        help="repeats of each measurement; the one with the lowest median counts (default 3)",
    )
    parser.add_argument(
        "--rt-seconds",
        type=float,
        default=60.0,
        metavar="S",
        help="seconds of the real-time run and of cyclictest (default 60; 0 skips both)",
    )
    parser.add_argument(
        "--joints",
        default="2,3,4,6,8,12",
        metavar="N1,N2,...",
        help='joint counts of the scaling table (default 2,3,4,6,8,12; "" skips it)',
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="also write the figures as JSON")
    args = parser.parse_args()
    try:
        joints = [int(x) for x in args.joints.split(",") if x.strip()]
        if args.ticks < 100 or args.repeat < 1 or any(n < 1 for n in joints):
            raise ValueError
    except ValueError:
        print("bench: error: --ticks >= 100, --repeat >= 1, --joints a list of counts >= 1",
              file=sys.stderr)  # fmt: skip
        return 2
    try:
        cfg = config.load(Path(args.config))
        return run(args, cfg, joints)
    except TeleopError as err:
        print(f"bench: error: {err}", file=sys.stderr)
        return 2


def run(args, cfg, joints: list[int]) -> int:
    out: dict = {
        "machine": {
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "pinocchio": pin.__version__,
            "numpy": np.__version__,
        }
    }
    m = out["machine"]
    print(f"machine: {m['processor']}, {m['cpus']} CPUs, Python {m['python']}, "
          f"Pinocchio {m['pinocchio']}, numpy {m['numpy']}")  # fmt: skip
    print(f"config: {args.config}   ticks: {args.ticks} x {args.repeat}")
    out["granted"] = grant()
    print("real-time grant: " + "; ".join(out["granted"]))

    print("\ntick cost (fast mode)")
    floor = pinocchio_floor(cfg)
    print(line("Pinocchio calls alone (6 per tick)", floor))
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        full = full_tick(cfg, args.ticks, args.repeat, tmp)
        samples = record_feedback(cfg, args.ticks)
        ctrl = best_of([controller_side(cfg, samples, args.ticks) for _ in range(args.repeat)])
        alone = [each_site_alone(cfg, samples, args.ticks) for _ in range(args.repeat)]
        sites = {name: best_of([a[name] for a in alone]) for name in ("hsi", "to")}
        print(line("full tick, recording off", full["plain"]))
        print(line("full tick, recording on", full["recorded"]))
        print(line("controller side (no plant)", ctrl))
        print(line("  HSI site alone (controller side)", sites["hsi"]))
        print(line("  TO site alone (controller side)", sites["to"]))
        rec = full["recorded"]["median"] - full["plain"]["median"]
        print(f"  recording adds {rec:.1f} us per tick (median); fast mode runs "
              f"{1e3 / full['recorded']['median']:.0f}x real time with recording on")  # fmt: skip
        writer = ", ".join(f"{x:.1f}" for x in full["writer_cpu_us"])
        fixed = ", ".join(f"{x:.0f}" for x in full["writer_fixed_ms"])
        beyond = ", ".join(f"{x:.1f}" for x in full["writer_per_tick_us"])
        size = ", ".join(f"{x:.0f}" for x in full["log_bytes_per_tick"])
        print(f"  the log writer process (beside the tick, on the other core if there is one) "
              f"used {writer} us of CPU per tick over runs of {args.ticks} ticks; a writer "
              f"started and closed without a tick {fixed} ms; beyond that {beyond} us per "
              f"tick (goal, issue 27: <= 5); the log {size} bytes per tick")  # fmt: skip
        fl = full["floors"]
        print(f"  the writer's floors: the SDK's log call alone {fl['sdk_log_us_per_tick']:.2f} us "
              f"per tick ({fl['messages_per_tick']} messages; the writer before its own "
              f"chunks); the writer's own chunks of the same payloads "
              f"{fl['chunks_us_per_tick']:.2f} us per tick; a bare fork and exit of this "
              f"process {fl['fork_exit_ms']:.1f} ms")  # fmt: skip
        out.update(pinocchio_floor_us=floor, full_tick_us=full, controller_side_us=ctrl,
                   site_alone_us=sites)  # fmt: skip

        if args.rt_seconds > 0:
            print(f"\nreal-time mode: {args.rt_seconds:g} s at {cfg.rate_hz:g} Hz, recording on")
            rt = realtime(cfg, args.rt_seconds, tmp)
            t = rt["timing"]
            late, comp = t["lateness_us"], t["compute_us"]
            for label, s in (("deadline lateness", late), ("tick compute", comp)):
                print(f"  {label:<20} p50 {s['p50']:6.1f}  p99 {s['p99']:6.1f}  "
                      f"p99.9 {s['p99.9']:7.1f}  max {s['max']:8.1f} us")  # fmt: skip
            print(f"  ticks started over a period late: {t['late_over_period']} of {t['ticks']};"
                  f" missed deadlines: {t['missed_deadlines']}")  # fmt: skip
            print(f"  the log writer process used {rt['writer_cpu_us']:.1f} us of CPU per tick; "
                  f"log {rt['log_bytes_per_tick']:.0f} bytes per tick")  # fmt: skip
            for note in rt["notes"]:
                print(f"  note: {note}")
            out["realtime"] = rt
            print(f"host baseline: cyclictest, {args.rt_seconds:g} s, the same grant")
            host = host_baseline(args.rt_seconds, cfg.rate_hz)
            if host is None:
                print("  cyclictest not installed (Debian: apt install rt-tests); skipped")
            elif "error" in host:
                print(f"  cyclictest failed: {host['error']}")
            else:
                print(f"  wake-up latency     p50 {host['p50']:6.1f}  p99 {host['p99']:6.1f}  "
                      f"p99.9 {host['p99.9']:7.1f}  max {host['max']:8.1f} us")  # fmt: skip
                print(f"  wake-ups over a period late: {host['late_over_period']} of "
                      f"{host['wakeups']} (a thread that does nothing else)")  # fmt: skip
            out["host_baseline"] = host

        print("\nchannel kinds (full tick, recording off, 20 ms delay, alternated)")
        kinds = channel_kinds(Path(args.config), args.ticks, args.repeat)
        base = next(iter(kinds.values()))
        for label, figures in kinds.items():
            d_min, d_med = (figures[k] - base[k] for k in ("min", "median"))
            print(line(label, figures) + f"   vs plain wave: min {d_min:+.2f}, median "
                  f"{d_med:+.2f} us")  # fmt: skip
        out["channel_kinds_us"] = kinds

        print("\nmappings (full tick, both sites, recording off, 20 ms delay, alternated)")
        maps = mappings(Path(args.config), args.ticks, args.repeat)
        base = next(iter(maps.values()))
        for label, figures in maps.items():
            d_min, d_med = (figures[k] - base[k] for k in ("min", "median"))
            print(line(label, figures) + f"   vs identity: min {d_min:+.2f}, median "
                  f"{d_med:+.2f} us")  # fmt: skip
        out["mappings_us"] = maps

        if joints:  # --joints "" skips the scaling table
            print("\nscaling with the number of joints (planar chains, full tick, recording off)")
            rows = scaling(joints, max(args.ticks // 2, 100), args.repeat, tmp)
            base = rows[0]["median"]
            print(f"  {'joints':>6}  {'min':>6}  {'median':>6}  {'p99':>6} us   median / first row"
                  "   the task-space map per site (median vs joint to joint): plane, "
                  "position, pose; the map's Pinocchio floor (one frame Jacobian)")  # fmt: skip
            for r in rows:
                adds = "  ".join(
                    f"{label} {cost:+5.2f}" if (cost := map_cost(r, label)) is not None
                    else f"{label}   -  " for label in ("plane", "position", "pose")
                )  # fmt: skip
                print(f"  {r['joints']:>6}  {r['min']:6.1f}  {r['median']:6.1f}  {r['p99']:6.1f}"
                      f"      {r['median'] / base:5.2f}          {adds}  us   floor "
                      f"{r['map_floor']['median']:4.2f} us")  # fmt: skip
            print(f"  goal (issue 26): the map adds <= {MAP_GOAL_US:g} us per site at 6 joints;"
                  " the floor is in it (the map's Jacobian is a Pinocchio call from Python)")
            out["scaling"] = rows
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
