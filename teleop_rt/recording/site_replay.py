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
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from teleop_rt.com.link import Link
from teleop_rt.com.port import Packet
from teleop_rt.com.zenoh_link import Arrival, shared_parts
from teleop_rt.declarations import port_symbol
from teleop_rt.errors import ConfigError
from teleop_rt.loop import TickClock
from teleop_rt.recording.reader import LogData, read_log, require_ticks
from teleop_rt.recording.recorder import default_log_path
from teleop_rt.recording.replay import (
    logged_inputs,
    replay_config,
    replay_operator,
    take_logged_inputs,
)
from teleop_rt.recording.schema import LogLayout
from teleop_rt.recording.site_log import site_log_path, site_recorder
from teleop_rt.runner import LoopHooks, LoopOutcome, run_loop
from teleop_rt.site import HsiSite, Site, ToSite, bring_to_rest

COMPARED = ("/port",)  # with the robot's topic: what a replay without overrides reproduces


class LoggedLink(Link):
    """The peer's packets from a site's log: at tick k the one the site used at tick k, each
    packet field the log's /link declares to hold (``teleop_rt.declarations.LINK_LOG``) handed
    back as it was logged."""

    def __init__(
        self, link: np.ndarray, site: Site, arrival: Arrival | None, layout: LogLayout
    ) -> None:
        self.rows, self.site, self.arrival = link, site, arrival
        topic = next(t for t in layout.topics if t.name == "/link")
        fields = [(f.name, f.source) for f in topic.fields[2:] if f.source is not None]
        self.vectors = [(name, attr) for name, (owner, attr) in fields
                        if owner == "packet" and attr in Packet.VECTORS]  # fmt: skip
        self.numbers = [(name, attr, attr in Packet.INTS) for name, (owner, attr) in fields
                        if owner == "packet" and attr not in Packet.VECTORS]  # fmt: skip
        self.arrivals = [(name, attr) for name, (owner, attr) in fields if owner == "arrival"]
        # the HSI's coupling state each packet carried (schema 3): a TO that followed a live
        # clutch follows it again (an older log's packets said nothing of it: coupled)
        self.engaged = "engaged" in (link.dtype.names or ())

    def send(self, side: int, packet: Packet) -> None:
        pass  # the partner does not listen: its packets are the logged ones

    def receive(self, side: int, into: Packet) -> None:
        row = self.rows[self.site.tick]
        if row["valid"]:
            for name, attr in self.vectors:
                getattr(into, attr)[:] = row[name]
            for name, attr, is_int in self.numbers:  # (a scalar is a float, an Int an int)
                setattr(into, attr, int(row[name]) if is_int else float(row[name]))
            into.tick = into.seq = int(row["sender_tick"])
            into.valid = 1
            if not self.engaged:
                into.engaged = 1
        else:  # as the playout hands out a packet that is not there: zeros
            into.f[:] = 0.0
            into.i[:] = 0
        a = self.arrival
        if a is not None:  # the replay's log holds the same /link
            for name, attr in self.arrivals:
                setattr(a, attr, float(row[name]))

    def end_tick(self, side: int) -> None:
        pass


def build_site_replay(data: LogData, overrides: list[str]) -> Site:
    """The site of ``data`` on the simulated backend with ``overrides``; refused (ConfigError)
    when they change what both sites share."""
    require_ticks(data)
    cfg = replay_config(data, overrides)
    cls = HsiSite if data.site == "hsi" else ToSite
    site = cls(cfg, "sim", replay_operator(cfg, data) if data.site == "hsi" else None)
    take_logged_inputs(site, data)
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
    arrival = recorder.session.arrival if recorder else None
    link = LoggedLink(data.topics["/link"], site, arrival, data.layout)
    run = _ReplayRun(site, link, data, logged_inputs(data))
    run_loop(run, data.ticks, cfg.dt, [site.backend], recorder=recorder)
    assert run.summary is not None  # (finish runs however the loop ends)
    return run.summary


class _ReplayRun(LoopHooks):
    """A site's replay in the loop: its ticks against the logged packets, its staged stop, its
    summary."""

    def __init__(
        self, site: Site, link: LoggedLink, data: LogData, inputs: np.ndarray | None
    ) -> None:
        self.site, self.link, self.data = site, link, data
        self.inputs = inputs  # the operator's live inputs as the log has them (or None)
        self.summary: dict | None = None

    def step(self) -> None:
        if self.inputs is not None:
            self.site.feedback.inputs = int(self.inputs[self.site.tick])
        self.site.sense(self.link)
        self.site.update(self.link)

    def bring_to_rest(self, clock: TickClock) -> str:
        site = self.site
        return bring_to_rest([site], site, clock.wait, site.cfg.safety.stop_max_ticks)

    def finish(self, out: LoopOutcome) -> dict:
        site, cfg = self.site, self.site.cfg
        self.summary = {
            "name": cfg.name,
            "site": self.data.site,
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
        return self.summary


def site_figures(data: LogData) -> dict:
    """A site log's own figures (see the module's doc)."""
    robot, port = data.topics[f"/{data.site}"], data.topics["/port"]
    flow, effort = (port_symbol(data.site, x) for x in ("flow", "effort"))
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


@dataclass
class SiteReplay:
    """What a site's replay found: ``figures`` (both logs' figures and the comparison: what
    ``--json`` prints, what ``teleop_rt.report.print_site_comparison`` shows), how the replay
    ended (its summary) and its log (``log_path``: the temporary one under ``--no-log``)."""

    figures: dict
    summary: dict
    log_path: Path

    @property
    def log_status(self) -> dict:
        return self.figures["recording"]


def replay_site(
    data: LogData, overrides: list[str], log_out: str | None, keep_log: bool, replay_of: str
) -> SiteReplay:
    """``teleop-rt replay SITE.mcap``: run the site of ``data`` against its partner's logged
    packets, record it (to ``log_out``, by default logs/<name>-replay-<UTC time>.<site>.mcap;
    without ``keep_log`` to a temporary log, the figures being read from a log) and compare
    both logs. Prints nothing: the command line does."""
    site = build_site_replay(data, overrides)
    metadata = {
        "replay_of": replay_of,
        "overrides": json.dumps(overrides),
        **({"config": data.meta["config"]} if "config" in data.meta else {}),
    }
    scratch = None
    if not keep_log:
        scratch = tempfile.TemporaryDirectory(prefix="teleop-rt-replay-")
        path = Path(scratch.name) / f"replay.{data.site}.mcap"
    elif log_out:
        path = Path(log_out)
    else:
        path = site_log_path(default_log_path(site.cfg.name + "-replay"), data.site)
    try:
        recorder = site_recorder(site, path, wait_for_room=True, metadata=metadata)
        recorder.describe({"session_id": data.meta.get("session_id", "")})
        summary = run_site_replay(site, data, recorder)
        status = recorder.status()
        replayed = read_log(recorder.path)
        figures = {
            "original": site_figures(data),
            "replay": site_figures(replayed),
            **compare(data, replayed),
            "site": data.site,
            "overrides": overrides,
            "log": str(recorder.path) if keep_log else None,
            "recording": status,
            "truncated_input": data.truncated,
        }
    finally:
        if scratch is not None:
            scratch.cleanup()
    return SiteReplay(figures, summary, recorder.path)
