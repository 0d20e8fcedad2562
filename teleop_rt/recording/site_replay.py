"""``teleop-rt replay SITE.mcap``: re-run one site of a two-site session against its partner's
logged packets.

The partner is the packets the site used, tick by tick, as its log's ``/link`` holds them (the
peer's port input, wave and energy, or a zero packet where none was due), not a simulated
robot of the other side. Why: that is what the site really met, network and all (lost packets
as zero waves, a partner on real hardware, a person at the HSI); a simulated partner in a
one-process session would meet a lossless link and a partner of the config's making, so even
without overrides its figures would differ from the log's for reasons that are not the site's.
With the logged packets the site's robot is re-run (simulated, from the config in the log; an
HSI's operator from its logged input, as ``replay`` of a session's log does) and, without
overrides, reproduces every logged signal of the site bit for bit: the comparison says
``identical``. With overrides of the site's own parameters (its gains, virtual mass, safety,
the plant) it shows what this site would have done given the same incoming waves; the partner
does not react (open loop), so overrides of what both sites share (the rate, the delay, the
channel) are refused: the logged packets were made for the original ones.

Figures of either log (``site_figures``): ticks, the energy into the channel at this port
(last and minimum), and the integral of the squared controller input (eq 4, 14: tau_h - tau_c at
the HSI, omega_t - v_t at the TO), per joint; and how far the replay's joint angles moved from
the log's.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from teleop_rt.com.link import Link
from teleop_rt.com.port import Packet
from teleop_rt.com.zenoh_link import Arrival, shared_parts
from teleop_rt.errors import ConfigError
from teleop_rt.recording.reader import LogData, read_log, require_ticks
from teleop_rt.recording.replay import replay_config, replay_operator
from teleop_rt.recording.schema import PACKET_EXTRAS, PORT_NAMES
from teleop_rt.runner import run_loop
from teleop_rt.site import HsiSite, Site, ToSite, bring_to_rest

COMPARED = ("/port",)  # with the robot's topic: what a replay without overrides reproduces


class LoggedLink(Link):
    """The peer's packets from a site's log: at tick k the one the site used at tick k."""

    def __init__(self, link: np.ndarray, site: Site, arrival: Arrival | None) -> None:
        self.rows, self.site, self.arrival = link, site, arrival

    def send(self, side: int, packet: Packet) -> None:
        pass  # the partner does not listen: its packets are the logged ones

    def receive(self, side: int, into: Packet) -> None:
        row = self.rows[self.site.tick]
        if row["valid"]:
            into.x[:] = row["x"]
            into.wave[:] = row["wave"]
            for name in PACKET_EXTRAS:
                getattr(into, name)[:] = row[name]
            into.energy = float(row["peer_energy"])
            into.tick = into.seq = int(row["sender_tick"])
            into.valid = 1
        else:  # as the playout hands out a packet that is not there: zeros
            into.f[:] = 0.0
            into.i[:] = 0
        a = self.arrival
        if a is not None:  # the replay's log holds the same /link
            a.sender_tick, a.arrival_tick = float(row["sender_tick"]), float(row["arrival_tick"])
            a.one_way_delay_us, a.valid = float(row["one_way_delay_us"]), float(row["valid"])

    def end_tick(self, side: int) -> None:
        pass


def build_site_replay(data: LogData, overrides: list[str]) -> Site:
    """The site of ``data`` on the simulated backend with ``overrides``; refused (ConfigError)
    when they change what both sites share."""
    require_ticks(data)
    cfg = replay_config(data, overrides)
    cls = HsiSite if data.site == "hsi" else ToSite
    site = cls(cfg, "sim", replay_operator(cfg, data) if data.site == "hsi" else None)
    shared = shared_parts(cfg, site.n)
    if shared["config_hash"] != data.meta.get("config_hash"):
        original = replay_config(data, [])
        before = shared_parts(original, site.n)
        changed = ", ".join(k for k in shared if k != "config_hash" and shared[k] != before[k])
        raise ConfigError(
            f"--set changes what both sites share ({changed or 'the config hash'}): "
            f"{data.path} replays against its partner's logged packets, which were made for the "
            "original; replay a session's log to change the channel"
        )
    return site


def run_site_replay(site: Site, data: LogData, recorder) -> dict:
    """Run the site tick-locked against the logged packets; its summary (a dict)."""
    cfg = site.cfg
    link = LoggedLink(data.topics["/link"], site, recorder.session.arrival if recorder else None)
    summary: list[dict] = []

    def step() -> None:
        site.sense(link)
        site.update(link)

    def finish(out) -> dict:
        summary.append(
            {
                "name": cfg.name,
                "site": data.site,
                "ticks": out.stats.count,
                "simulated_time_s": out.stats.count * cfg.dt,
                "delay_ticks": cfg.delay_ticks,
                "port_energy_j": site.port.total_energy,
                "timing": out.timing(),
                "realtime": False,
                "notes": out.notes,
                "stopped_early": out.stopped_early,
                "stop_signal": out.stop.signum,
                "safety_stop": out.safety_stop,
                "saturated_ticks": site.guard.saturated_ticks,
            }  # fmt: skip
        )
        return summary[0]

    run_loop(
        step, data.ticks, cfg.dt, [site.backend],
        lambda clock: bring_to_rest([site], site, clock.wait, cfg.safety.stop_max_ticks),
        recorder=recorder, finish=finish,
    )  # fmt: skip
    return summary[0]


def site_figures(data: LogData) -> dict:
    """A site log's own figures (see the module's doc)."""
    robot, port = data.topics[f"/{data.site}"], data.topics["/port"]
    flow, effort = PORT_NAMES[data.site][:2]
    if data.site == "hsi":
        error = robot["tau_ext"] - port[effort]  # tau_h - tau_c
    else:
        error = port[flow] - robot["v"]  # omega_t - v_t
    dt, n = data.dt, data.layout.n
    tracking = (
        [float(x) for x in np.cumsum(error * error * dt, axis=0)[-1]] if len(error) else [0.0] * n
    )
    energy = port["total_energy"]
    return {
        "ticks": data.ticks,
        "port_energy_j": float(energy[-1]) if len(energy) else 0.0,
        "min_port_energy_j": min(0.0, float(energy.min())) if len(energy) else 0.0,
        "controller_input": tracking,
        "controller_input_total": float(sum(tracking)),
        "safety_stop": bool((data.summary or {}).get("safety_stop")),
    }


def compare(original: LogData, replay: LogData) -> dict:
    """How far the replay's signals are from the log's, over the ticks both hold."""
    k = min(original.ticks, replay.ticks)
    name = f"/{original.site}"
    a, b = original.topics[name][:k], replay.topics[name][:k]
    dq = float(np.abs(a["q"] - b["q"]).max()) if k else 0.0
    same = k == original.ticks == replay.ticks
    for topic in (name, *COMPARED):
        x, y = original.topics[topic][:k], replay.topics[topic][:k]
        same = same and all(np.array_equal(x[f], y[f]) for f in (x.dtype.names or ()) if f != "t")
    return {"max_abs_q_difference_rad": dq, "identical": bool(same)}


def replay_site_main(args, data: LogData, gap_note: str | None, recorder_for) -> int:
    """``teleop-rt replay SITE.mcap``: run it, print both logs' figures side by side; the exit
    code (0; 3 a safety stop; 4 the replay's log is incomplete)."""
    from teleop_rt.report import print_site_comparison

    if args.plot:
        raise ConfigError("--plot draws both robots; a site's log holds one: plot a session's log")
    if gap_note:
        print(f"teleop-rt: warning: {gap_note}", file=sys.stderr)
    site = build_site_replay(data, args.overrides)
    metadata = {
        "replay_of": str(args.log),
        "overrides": json.dumps(args.overrides),
        **({"config": data.meta["config"]} if "config" in data.meta else {}),
    }
    scratch = None
    path: Path | None
    if args.no_log:  # the figures are read from a log: a temporary one
        scratch = tempfile.TemporaryDirectory(prefix="teleop-rt-replay-")
        path = Path(scratch.name) / f"replay.{data.site}.mcap"
    else:
        path = Path(args.log_out) if args.log_out else None
    try:
        recorder = recorder_for(site, path, data.site, metadata)
        recorder.describe({"session_id": data.meta.get("session_id", "")})
        summary = run_site_replay(site, data, recorder)
        status = recorder.status()
        replayed = read_log(recorder.path)
        out = {
            "original": site_figures(data),
            "replay": site_figures(replayed),
            **compare(data, replayed),
            "site": data.site,
            "overrides": args.overrides,
            "log": None if args.no_log else str(recorder.path),
            "recording": status,
            "truncated_input": data.truncated,
        }
    finally:
        if scratch is not None:
            scratch.cleanup()
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        print()
    else:
        if data.truncated:
            print(f"note: {args.log} was cut short ({data.cut_reason}); replayed what it holds")
        print_site_comparison(out)
        if out["log"]:
            print(f"replay log: {out['log']}")
    if summary["safety_stop"]:
        return 3
    if not status["complete"]:
        print(f"teleop-rt: log {recorder.path} is incomplete: {status['failure']}",
              file=sys.stderr)  # fmt: skip
        return 4
    return 130 if summary["stopped_early"] else 0
