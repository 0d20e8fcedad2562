"""The link between two sites in separate processes (or machines): packets over Zenoh.

One ``ZenohLink`` per site. Its packets go out once complete (``end_tick``: encoded into a
preallocated buffer, ``teleop_rt.com.wire``, and handed to the transport's sender thread); the
peer's arrive on Zenoh's thread into the playout buffer (``teleop_rt.com.playout``: the packet
the peer sent at tick k - D is used at tick k if it has arrived, else a passive zero packet).

Before any motor is enabled the two sites shake hands (``handshake``): each publishes what it
runs (joints, rate, delay, the channel, a hash of these) until it hears the other; a mismatch is
a refusal naming the field. The HSI site chooses the session id and a start time on the wall
clock; the TO starts only once it has heard the HSI (its robot is not enabled before) and both
start their tick clocks at that instant, so that their tick counts agree (on one host exactly;
across hosts as well as their clocks agree: see README, "Two sites over a network").

Per tick the link can say which of the peer's packets it handed the site (``Arrival``: its
sender tick, the tick it arrived at, its one-way delay, or none): a site's log records it.

A site that hears nothing from its peer for ``link.peer_timeout_ms`` stops its robot: the
silence is a ``SafetyStop`` raised at the tick that notices it (the staged stop follows).

Clocks that drift: across hosts the two tick clocks run at rates that differ by tens of ppm.
The receiver follows the sender's (``teleop_rt.com.drift``): it tracks the floor of the
arrivals' lateness, measured on its own clock, over windows of a second and moves the
playout by a whole tick when the floor has slid by 3/4 tick for a whole window, playing a
zero packet or skipping one (never a packet twice). ``link.zenoh.<site>.clock_ppm`` makes a
site's clock run off on purpose, for tests.

``link.impairment`` applies here too, in real time: each site draws its own direction's fate
of every packet from ``teleop_rt.com.impairment`` (stream 0 at the HSI, 1 at the TO, as the
in-process ``ImpairedLink``: the same seed decides the same per packet in both) and hands the
copies that survive to the transport's sender thread with the instant each is due (send
instant plus its delay), which holds them in a preallocated pool (``teleop_rt.com.hold``)
and publishes each at its instant: lost never, duplicated twice, reordered ones at once.
"""

from __future__ import annotations

import hashlib
import json
import math
import random
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from teleop_rt.com.drift import DriftFollower
from teleop_rt.com.hold import HeldPackets
from teleop_rt.com.impairment import MAX_ARRIVALS, Impairment
from teleop_rt.com.link import Link
from teleop_rt.com.playout import Receiver
from teleop_rt.com.port import HSI, Packet
from teleop_rt.com.wire import OK, STALE, WireBuffer, encode_into, wire_size
from teleop_rt.com.zenoh_transport import ZenohTransport, zenoh_config
from teleop_rt.errors import ConfigError, SafetyStop, TeleopError
from teleop_rt.flat import Block, Scalar

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig

NAMES = ("hsi", "to")
ARRIVAL_SLOTS = 4096  # arrivals remembered by sender tick (at least 2 (D + early slack) + 1)


class Arrival(Block):
    """The peer's packet a site used this tick, as floats for the site's log row."""

    sender_tick = Scalar("the peer's tick of the packet used; -1: none was there")
    arrival_tick = Scalar("this site's tick when it arrived; -1: none")
    one_way_delay_us = Scalar("its sender's time to its arrival (one host); NaN: none")
    valid = Scalar("1: the packet due was there; 0: a zero packet")

    def __init__(self) -> None:
        super().__init__(1)
        self.none()

    def none(self) -> None:
        self.sender_tick = self.arrival_tick = -1.0
        self.one_way_delay_us = math.nan
        self.valid = 0.0


class HandshakeError(TeleopError):
    """The peer site never appeared, or runs another session (exit code 5)."""

    exit_code = 5


def shared_parts(cfg: SessionConfig, joints: int) -> dict:
    """What both sites must agree on, and a hash of it."""
    parts = {
        "name": cfg.name,
        "joints": joints,
        "rate_hz": cfg.rate_hz,
        "delay_ticks": cfg.delay_ticks,
        "channel": cfg.channel.model_dump(mode="json"),
    }
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]
    return {**parts, "config_hash": digest}


class ZenohLink(Link):
    """Site ``side``'s end of a Zenoh link for the session of ``cfg``."""

    def __init__(self, cfg: SessionConfig, side: int, n: int, clock_tick: Any) -> None:
        """``clock_tick()``: the site's current tick (where an arrival is counted)."""
        spec = cfg.link
        self.check(cfg)
        self.cfg, self.side, self.n = cfg, side, n
        self.name, self.peer = NAMES[side], NAMES[1 - side]
        self.base = f"{spec.key}/{cfg.name}"
        ends = getattr(spec.zenoh, self.name)
        tls = spec.zenoh.tls
        files = None
        if tls is not None:
            own = getattr(tls, self.name)
            files = {"root_ca": tls.root_ca, "certificate": own.certificate,
                     "private_key": own.private_key}  # fmt: skip
        config = zenoh_config(ends.listen, ends.connect, files, spec.zenoh.mode)
        # this direction's impairment and the hold its surviving copies wait in
        self.impairment: Impairment | None = None
        hold = None
        if spec.impairment is not None:
            self.impairment = Impairment(spec.impairment, cfg.dt, stream=side)
            slack = 64  # ticks the sender thread may fall behind before packets are refused
            slots = MAX_ARRIVALS * (self.impairment.max_delay_ticks + slack)
            hold = HeldPackets(wire_size(n), slots)
        self.transport = ZenohTransport(config, f"{self.base}/{self.name}/waves", hold=hold)
        # this site's tick period in real time: a clock clock_ppm fast counts its ticks sooner
        self.period_ns = cfg.dt * 1e9 / (1.0 + ends.clock_ppm * 1e-6)
        self.start_ns = 0
        self.drift: DriftFollower | None = None
        self._tick = clock_tick
        self._lock = threading.Lock()
        self._wire = WireBuffer(n)
        self._packet: Packet | None = None
        self.receiver: Receiver | None = None
        self.session_id = 0
        self.timeout_ns = round(spec.peer_timeout_ms * 1e6)
        self.last_arrival_ns = 0
        self.sent = 0
        # one-way delay of every accepted packet, ns (sender and receiver on one host share
        # CLOCK_MONOTONIC: across hosts this is meaningless and only ticks compare)
        self.delays_ns = np.zeros(cfg.n_ticks + 10_000, dtype=np.int64)
        self.n_delays = 0
        # per sender tick (modulo the slots): when its first copy arrived, and its delay
        slots = max(ARRIVAL_SLOTS, 2 * (cfg.delay_ticks + 64))
        self._arrived = np.full((slots, 3), -1, dtype=np.int64)  # sender tick, tick, delay ns
        self.arrival: Arrival | None = None  # filled at every receive when set
        self._warm_up()

    @staticmethod
    def check(cfg: SessionConfig) -> None:
        """ConfigError if ``cfg`` cannot run over a network (before anything is opened)."""
        if cfg.delay_ticks < 1:
            raise ConfigError(
                "channel.delay_ms: a link between processes needs a delay of at least one tick "
                f"({1000.0 / cfg.rate_hz:g} ms): the packets take time"
            )

    def _warm_up(self) -> None:
        """Load (or compile) the codec's and the playout's kernels now, not at the first tick:
        one packet through a scratch receiver."""
        scratch, into = Packet(self.n), Packet(self.n)
        scratch.seq = scratch.tick = 1
        receiver = Receiver(self.n, self.cfg.delay_ticks, 1)
        receiver.arrive(1, encode_into(WireBuffer(self.n), scratch, 1, 0))
        receiver.take(1 + self.cfg.delay_ticks, into)

    # --- before the loop --------------------------------------------------------------------
    def handshake(self, timeout_s: float | None = None) -> int:
        """Agree with the peer on the session; the wall-clock time (ns) to start at. Raises
        ``HandshakeError`` on a mismatch or when the peer does not appear in time."""
        timeout_s = self.cfg.link.handshake_timeout_s if timeout_s is None else timeout_s
        session = self.transport.session
        mine = {"site": self.name, **shared_parts(self.cfg, self.n)}
        if self.side == HSI:
            mine["session_id"] = random.getrandbits(63) or 1
        heard: dict[str, Any] = {}

        def on_hello(sample: Any) -> None:
            try:
                heard.update(json.loads(sample.payload.to_bytes()))
            except ValueError:
                pass  # not a hello of ours: ignored (the waves' decoder counts its own)

        hello = session.declare_publisher(f"{self.base}/{self.name}/hello")
        listener = session.declare_subscriber(f"{self.base}/{self.peer}/hello", on_hello)
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                hello.put(json.dumps(mine))
                if heard:
                    self._check_compatible(mine, heard)
                    if self.side == HSI:
                        if "start_ns" not in mine:  # the TO is there: when both start
                            mine["start_ns"] = time.time_ns() + 300_000_000
                        elif heard.get("start_ns") == mine["start_ns"]:
                            break  # the TO has it
                    elif "start_ns" in heard:
                        mine["session_id"], mine["start_ns"] = (
                            heard["session_id"],
                            heard["start_ns"],
                        )
                        for _ in range(5):  # the HSI may miss one
                            hello.put(json.dumps(mine))
                            time.sleep(0.01)
                        break
                if time.monotonic() > deadline:
                    raise HandshakeError(
                        f"link: the {self.peer} site did not answer within {timeout_s:g} s "
                        f"(key {self.base}/{self.peer}, endpoints "
                        f"{self._endpoints_text()})"
                    )
                time.sleep(0.02)
        finally:
            listener.undeclare()
            hello.undeclare()
        self.session_id = int(mine["session_id"])
        self.receiver = Receiver(
            self.n, self.cfg.delay_ticks, self.session_id, policy=self.cfg.link.playout
        )
        self.drift = DriftFollower(self.receiver.playout, self.cfg.link.max_drift_ppm)
        self.transport.listen(f"{self.base}/{self.peer}/waves", self._arrive)
        return int(mine["start_ns"])

    def _check_compatible(self, mine: dict, theirs: dict) -> None:
        if theirs.get("site") != self.peer:
            raise HandshakeError(f"link: a second {self.name} site answers on {self.base}")
        for key in ("joints", "rate_hz", "delay_ticks", "channel", "config_hash"):
            if theirs.get(key) != mine[key]:
                raise HandshakeError(
                    f"link: the {self.peer} site runs another session: {key} is "
                    f"{theirs.get(key)!r} there, {mine[key]!r} here"
                )

    def _endpoints_text(self) -> str:
        ends = getattr(self.cfg.link.zenoh, self.name)
        return ", ".join([*(f"listen {e}" for e in ends.listen),
                          *(f"connect {e}" for e in ends.connect)]) or "none"  # fmt: skip

    def start(self) -> None:
        """The loop starts now: the peer's silence is counted from here, and the arrivals'
        times in ticks of this site's clock."""
        self.start_ns = self.last_arrival_ns = time.monotonic_ns()

    # --- the Link interface -------------------------------------------------------------------
    def _arrive(self, data: bytes) -> None:  # on Zenoh's thread
        receiver = self.receiver
        if receiver is None:
            return
        with self._lock:  # the playout's kernels release the GIL: one thread at a time
            k = self._tick()
            status = receiver.arrive(k, data)
            now = time.monotonic_ns()
            delay = now - receiver.decoder.sender_time_ns
            if status == OK:
                s = receiver.decoder.seen_tick
                row = self._arrived[s % len(self._arrived)]
                if row[0] != s:  # the first copy's
                    row[0], row[1], row[2] = s, k, delay
            if (status == OK or status == STALE) and self.start_ns:  # intact and ours
                ticks = (now - self.start_ns) / self.period_ns
                self.drift.arrival(ticks, receiver.decoder.seen_tick)  # type: ignore[union-attr]
        if status == OK:
            self.last_arrival_ns = now
            if self.n_delays < self.delays_ns.size:
                self.delays_ns[self.n_delays] = delay
                self.n_delays += 1

    def send(self, side: int, packet: Packet) -> None:
        self._packet = packet

    def receive(self, side: int, into: Packet) -> None:
        k = self._tick()
        silent = time.monotonic_ns() - self.last_arrival_ns
        if silent > self.timeout_ns:
            raise SafetyStop(
                f"tick {k}: link: nothing from the {self.peer} site for {silent / 1e6:.0f} ms "
                f"(link.peer_timeout_ms = {self.cfg.link.peer_timeout_ms:g})"
            )
        with self._lock:
            used = self.receiver.take(k, into)
            if self.arrival is not None:
                self._note_arrival(used, into.tick)

    def _note_arrival(self, used: int, s: int) -> None:
        a = self.arrival
        row = self._arrived[s % len(self._arrived)]
        if not used:
            a.none()
        elif row[0] == s:
            a.sender_tick, a.arrival_tick = s, row[1]
            a.one_way_delay_us, a.valid = row[2] / 1e3, 1.0
        else:  # (a packet is stored only after it was noted: not reached)
            a.sender_tick, a.valid = s, 1.0
            a.arrival_tick, a.one_way_delay_us = -1.0, math.nan

    def end_tick(self, side: int) -> None:
        now = time.monotonic_ns()
        packet = self._packet
        data = encode_into(self._wire, packet, self.session_id, now)
        impairment = self.impairment
        if impairment is None:
            self.transport.send(data, now)
        else:  # each surviving copy to the sender thread, with its instant
            delays = impairment.delays_ms
            for k in range(impairment.decide(packet.tick)):
                self.transport.send_at(data, now + int(delays[k] * 1e6))
        self.sent += 1

    # --- afterwards -----------------------------------------------------------------------------
    def stats(self) -> dict:
        """What the link did: this site's packets sent, and the peer's as received here."""
        received = self.receiver.stats() if self.receiver is not None else {}
        d = self.delays_ns[: self.n_delays] / 1e3
        delay_us = (
            {"min": float(d.min()), "p50": float(np.percentile(d, 50)),
             "p99": float(np.percentile(d, 99)), "max": float(d.max())} if d.size else None
        )  # fmt: skip
        out = {
            "sent": self.sent,
            "one_way_delay_us": delay_us,
            "send_replaced": self.transport.replaced,
            "send_errors": self.transport.send_errors,
            # how long after the tick handed it over (or after its instant, when held) each
            # packet went out: this site's part of the one-way delay
            "send_after_due_us": self.transport.late_out_us(),
            "from_peer": received,
        }
        if self.drift is not None:
            out["drift"] = self.drift.stats()
        imp = self.impairment
        if imp is not None:  # what this site's impairment stage did to its own packets
            out["impairment"] = {"decided": imp.decided, "lost": imp.lost,
                                 "duplicated": imp.duplicated, "reordered": imp.reordered,
                                 **self.transport.hold_stats()}  # fmt: skip
        return out

    def close(self) -> None:
        self.transport.close()
