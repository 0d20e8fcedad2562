"""The link between two sites in separate processes (or machines): packets over Zenoh.

One ``ZenohLink`` per site. Its packets go out once complete (``end_tick``: encoded into a
preallocated buffer, ``teleop_rt.com.wire``, and published by the tick: ``ZenohTransport.send``);
the peer's arrive on Zenoh's thread into the playout buffer (``teleop_rt.com.playout``: the packet
the peer sent at tick k - D is used at tick k if it has arrived, else a passive zero packet).

Before any motor is enabled the two sites shake hands (``handshake``): each publishes what it
runs (joints, rate, delay, the channel, a hash of these, its peer timeout) until it hears the
other; a mismatch is a refusal naming the field. The HSI site chooses the session id and a start
time on the wall clock; the TO starts only once it has heard the HSI (its robot is not enabled
before) and both start their tick clocks at that instant, so that their tick counts agree (on
one host exactly; across hosts as well as their clocks agree: see docs/network.md). A hello is
checked like a packet (``parse_hello``): anything but a JSON object of
the expected fields, a session id in [1, 2**63) and a start instant at most
``START_AHEAD_MAX_S`` ahead is ignored and counted by reason, never a traceback; a SIGINT or
SIGTERM ends the wait at once (``KeyboardInterrupt`` / ``Terminated``: exit 130 / 143).

Who may speak: without TLS nobody is authenticated, and the checks above only catch nonsense,
reflection and replay (docs/network.md: anyone who reaches the endpoint can drive the robots). With
``link.zenoh.tls`` each site's certificate must name its role in its subject CN
(``role_name``: ``hsi.<key>`` / ``to.<key>``, checked when the site starts), and the site's
Zenoh session runs an access-control list (``role_acl``) that denies, message by message,
everything but the peer role's certificate publishing the peer's keys: a certificate of the
same CA for the other role (or any other name) can neither feed this site nor read it.

Per tick the link can say which of the peer's packets it handed the site (``Arrival``: its
sender tick, the tick it arrived at, its one-way delay, or none): a site's log records it.

A site that hears nothing from its peer for ``link.peer_timeout_ms`` stops its robot: the
silence is a ``SafetyStop`` raised at the tick that notices it (the staged stop follows). It
counts from the start plus a grace of max(peer timeout, ``STARTUP_GRACE_S``): the first packet
may take longer on a loaded host. Only an arrival that passed every check and was new to the
playout (``Receiver.fresh``) counts as hearing the peer, and only such arrivals feed the drift
follower.

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
import signal
import threading
import time
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np
from cryptography import x509
from cryptography.x509.oid import NameOID

from teleop_rt.com.drift import DriftFollower
from teleop_rt.com.hold import HeldPackets
from teleop_rt.com.impairment import MAX_ARRIVALS, Impairment
from teleop_rt.com.link import Link
from teleop_rt.com.playout import Receiver
from teleop_rt.com.port import HSI, Packet
from teleop_rt.com.wire import VERSION, WireBuffer, encode_into, wire_size
from teleop_rt.com.zenoh_transport import ZenohTransport, zenoh_config
from teleop_rt.errors import ConfigError, SafetyStop, TeleopError
from teleop_rt.exit_signals import Terminated
from teleop_rt.flat import Block, Scalar
from teleop_rt.inputs import read_bounded
from teleop_rt.loop import StopSignals

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig

NAMES = ("hsi", "to")
ARRIVAL_SLOTS = 4096  # arrivals remembered by sender tick (at least 2 (D + early slack) + 1)
HELLO_MAX_BYTES = 4096  # a hello is a few hundred bytes; more is not one of ours
SESSION_ID_END = 1 << 63  # session ids are in [1, 2**63): what the wire's u64 carries as i64
START_LEAD_S = 0.3  # the HSI starts both sites this long after the TO answered
START_AHEAD_MAX_S = 10.0  # a hello's start instant further ahead is refused (a forged one)
STARTUP_GRACE_S = 0.5  # the peer timeout counts from start + max(this, the timeout)
WAIT_SLICE_S = 0.02  # the longest a wait sleeps before it looks for a stop signal
SILENT_FRACTION = 0.5  # a run that used fewer of the peer's packets due did not really run


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


def raise_if_stopped() -> None:
    """A SIGINT, SIGTERM or SIGHUP caught by the running loop's handler ends a wait before the
    loop: ``KeyboardInterrupt`` / ``Terminated``, which the CLI turns into exit 130 / 143 /
    129."""
    for stop in StopSignals.installed:
        if stop.requested:
            if stop.signum in (None, signal.SIGINT):
                raise KeyboardInterrupt
            raise Terminated(stop.signum)


def wait_until_ns(wall_ns: int) -> bool:
    """Sleep until the wall-clock instant ``wall_ns`` in short slices; False as soon as a stop
    signal is pending (the caller then starts no tick)."""
    while True:
        if StopSignals.pending():
            return False
        left = (wall_ns - time.time_ns()) / 1e9
        if left <= 0:
            return True
        time.sleep(min(left, WAIT_SLICE_S))


def _short(value: Any, limit: int = 80) -> str:
    """A peer's value for a one-line message: its repr, cut in the middle when long."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit // 2]}...{text[-limit // 2 :]}"


def _plain_int(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def parse_hello(raw: bytes, past_ns: int, now_ns: int | None = None) -> dict | str:
    """A peer's hello as a dict, or the reason it is not a valid one (its counter's name):
    a JSON object of at most ``HELLO_MAX_BYTES``, ``site`` hsi or to, ``session_id`` (required
    from the HSI) an int in [1, 2**63), ``start_ns`` an int no more than ``START_AHEAD_MAX_S``
    ahead of now nor ``past_ns`` behind it. The fields both sites must agree on are compared
    afterwards (a mismatch is a refusal naming the field)."""
    if len(raw) > HELLO_MAX_BYTES:
        return "size"
    try:
        hello = json.loads(raw)
    except (ValueError, RecursionError):  # (UnicodeDecodeError is a ValueError)
        return "not_json"
    if not isinstance(hello, dict):
        return "not_an_object"
    site = hello.get("site")
    if site not in NAMES:
        return "site"
    session = hello.get("session_id")
    if session is not None or site == "hsi":
        if not (_plain_int(session) and 1 <= session < SESSION_ID_END):
            return "session_id"
    start = hello.get("start_ns")
    if start is not None:
        now = time.time_ns() if now_ns is None else now_ns
        if not _plain_int(start):
            return "start_ns"
        if not now - past_ns <= start <= now + round(START_AHEAD_MAX_S * 1e9):
            return "start_ns_window"
    return hello


def _first_difference(theirs: dict, mine: dict, prefix: str) -> tuple[str, Any, Any]:
    """The first key (dotted, nested) whose value differs: its name, theirs, mine."""
    for key in sorted(set(theirs) | set(mine)):
        a, b = theirs.get(key), mine.get(key)
        if a != b:
            if isinstance(a, dict) and isinstance(b, dict):
                return _first_difference(a, b, f"{prefix}.{key}")
            return f"{prefix}.{key}", a, b
    return prefix, theirs, mine


def role_name(key: str, site: str) -> str:
    """The name site ``site``'s TLS certificate carries as its subject CN: ``hsi.<key>`` or
    ``to.<key>`` (the link's key, '/' written as '.')."""
    return f"{site}.{key.replace('/', '.')}"


def role_acl(base: str, me: str, peer: str, peer_cn: str) -> dict:
    """Zenoh's access control for site ``me`` (default deny): only a session whose certificate
    CN is ``peer_cn`` may publish the peer's keys to it, subscribe to this site's keys, or
    receive what it publishes. Zenoh applies it to every message of every link."""
    own = [f"{base}/{me}/waves", f"{base}/{me}/hello"]
    theirs = [f"{base}/{peer}/waves", f"{base}/{peer}/hello"]
    rules = [
        ("from the peer", "ingress", ["put"], theirs),
        ("the peer subscribes", "ingress", ["declare_subscriber"], own),
        ("to the peer", "egress", ["put"], own),
        ("this site subscribes", "egress", ["declare_subscriber"], theirs),
    ]
    allow = [{"id": rid, "permission": "allow", "flows": [flow], "messages": messages,
              "key_exprs": keys} for rid, flow, messages, keys in rules]  # fmt: skip
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": allow,
        "subjects": [{"id": "peer", "cert_common_names": [peer_cn]}],
        "policies": [{"rules": [r[0] for r in rules], "subjects": ["peer"]}],
    }


CERTIFICATE_MAX_BYTES = 1 << 20  # a PEM certificate (chain) is a few KiB


def certificate_names(path: Any) -> tuple[list[str], list[str]]:
    """A PEM certificate's subject CNs and subjectAltName DNS names (ConfigError if it cannot
    be read), parsed with ``cryptography``'s X.509 decoder."""
    pem = read_bounded(path, CERTIFICATE_MAX_BYTES, "link.zenoh.tls: certificate ")
    try:
        cert = x509.load_pem_x509_certificate(pem)
    except ValueError as err:
        raise ConfigError(f"link.zenoh.tls: cannot read the certificate {path} ({err})") from None
    cns = [str(a.value) for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        dns = san.get_values_for_type(x509.DNSName)
    except x509.ExtensionNotFound:
        dns = []
    return cns, dns


def shared_parts(cfg: SessionConfig, joints: int) -> dict:
    """What both sites must agree on, and a hash of it."""
    parts = {
        "wire_version": VERSION,  # (the packet's layout: a peer of another is refused)
        "name": cfg.name,
        "joints": joints,
        "rate_hz": cfg.rate_hz,
        "delay_ticks": cfg.delay_ticks,
        "channel": cfg.channel.model_dump(mode="json"),
    }
    digest = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]
    return {**parts, "config_hash": digest}


class LoopbackTransport:
    """Two links' transports in one process, without Zenoh: ``send`` keeps the tick's packet
    (copied, as ``ZenohTransport.send`` does), ``deliver`` hands it to the peer's receive
    callback, outside the ticks. A pair of ``ZenohLink`` over it runs the link's own code (the
    encoder, the receive path, the playout, the drift follower) back to back: the fast-mode
    figure of a site's tick that ``tools/bench_link.py`` puts beside the real-time one."""

    send_errors = 0

    def __init__(self, packet_bytes: int) -> None:
        self._out = bytearray(packet_bytes)
        self._pending = False
        self.on_bytes: Any = None

    def listen(self, key: str, on_bytes: Any) -> None:
        self.on_bytes = on_bytes

    def send(self, data: bytes | bytearray | memoryview, at_ns: int) -> None:
        self._out[:] = data
        self._pending = True

    def deliver(self, peer: LoopbackTransport) -> None:
        """The packet sent since the last delivery (if any) into ``peer``'s callback, as the
        bytes Zenoh's callback gets."""
        if self._pending and peer.on_bytes is not None:
            self._pending = False
            peer.on_bytes(bytes(self._out))

    def late_out_us(self) -> None:
        return None

    def put_us(self) -> None:
        return None

    def hold_stats(self) -> dict:
        return {}

    def close(self) -> None:
        return


class ZenohLink(Link):
    """Site ``side``'s end of a Zenoh link for the session of ``cfg``."""

    def __init__(
        self, cfg: SessionConfig, side: int, n: int, clock_tick: Any, transport: Any = None
    ) -> None:
        """``clock_tick()``: the site's current tick (where an arrival is counted);
        ``transport``: in place of a Zenoh session (``LoopbackTransport``: this link's own
        code between two sites of one process, for a benchmark's fast-mode figure)."""
        spec = cfg.link
        self.check(cfg)
        self.cfg, self.side, self.n = cfg, side, n
        self.name, self.peer = NAMES[side], NAMES[1 - side]
        self.base = f"{spec.key}/{cfg.name}"
        ends = getattr(spec.zenoh, self.name)
        tls = spec.zenoh.tls
        files = acl = None
        if tls is not None:
            own = getattr(tls, self.name)
            files = {"root_ca": tls.root_ca, "certificate": own.certificate,
                     "private_key": own.private_key}  # fmt: skip
            acl = role_acl(self.base, self.name, self.peer, role_name(spec.key, self.peer))
        config = zenoh_config(ends.listen, ends.connect, files, spec.zenoh.mode, acl)
        # this direction's impairment and the hold its surviving copies wait in
        self.impairment: Impairment | None = None
        hold = None
        if spec.impairment is not None:
            self.impairment = Impairment(spec.impairment, cfg.dt, stream=side)
            slack = 64  # ticks the sender thread may fall behind before packets are refused
            slots = MAX_ARRIVALS * (self.impairment.max_delay_ticks + slack)
            hold = HeldPackets(wire_size(n), slots)
        listening = (ends.listen, f"link.zenoh.{self.name}.listen")  # named if in use
        self.transport = transport or ZenohTransport(
            config, f"{self.base}/{self.name}/waves", wire_size(n), hold=hold, listen=listening
        )
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
        # a codec may be silent for its maximum interval: the timeout counts from there
        silent_ms = 0.0
        if cfg.channel.codec != "none":
            silent_ms = cfg.channel.deadband.max_interval_ticks * cfg.dt * 1e3
        self.timeout_ns = round((spec.peer_timeout_ms + silent_ms) * 1e6)
        self.grace_ns = max(0, round(STARTUP_GRACE_S * 1e9) - self.timeout_ns)
        self.last_arrival_ns = 0
        self._last_receive_ns = 0  # CLOCK_MONOTONIC of the previous receive; 0: none yet
        self.held_ns = round(spec.peer_timeout_ms * 1e6)  # this site's own gap that stops it
        self.heard = False  # a fresh packet of the peer has arrived since the start
        self.hellos_ignored: dict[str, int] = {}  # invalid hellos by reason
        self.sent = 0
        self.not_sent = 0  # ticks the codec sent nothing
        # the receiver (made by the handshake) notes the one-way delay of every fresh packet,
        # ns (sender and receiver on one host share CLOCK_MONOTONIC: across hosts this is
        # meaningless and only ticks compare), and per sender tick (modulo the slots) when its
        # first copy arrived, and its delay
        self._delay_capacity = cfg.n_ticks + 10_000
        self._arrival_slots = max(ARRIVAL_SLOTS, 2 * (cfg.delay_ticks + 64))
        self.arrival: Arrival | None = None  # filled at every receive when set
        self._warm_up()

    @staticmethod
    def check(cfg: SessionConfig, site: str | None = None) -> None:
        """ConfigError if ``cfg`` cannot run over a network (before anything is opened); with
        TLS, site ``site``'s certificate must name its role (``role_name``)."""
        if cfg.delay_ticks < 1:
            raise ConfigError(
                "channel.delay_ms: a link between processes needs a delay of at least one tick "
                f"({1000.0 / cfg.rate_hz:g} ms): the packets take time"
            )
        tls = cfg.link.zenoh.tls
        if tls is not None and site is not None:
            path = getattr(tls, site).certificate
            cns, _ = certificate_names(path)
            want = role_name(cfg.link.key, site)
            if cns != [want]:
                found = ", ".join(cns) or "none"
                raise ConfigError(
                    f"link.zenoh.tls.{site}.certificate: {path} names {found} as its subject CN; "
                    f"the {site} site's certificate must name its role: CN={want} (the peer "
                    "accepts only that name for this role)"
                )

    def _warm_up(self) -> None:
        """Load (or compile) the codec's and the playout's kernels now, not at the first tick:
        one packet through a scratch receiver."""
        scratch, into = Packet(self.n), Packet(self.n)
        scratch.seq = scratch.tick = 1
        receiver = Receiver(self.n, self.cfg.delay_ticks, 1, self.side)
        receiver.arrive(1, encode_into(WireBuffer(self.n), scratch, 1, 0, self.side))
        receiver.take(1 + self.cfg.delay_ticks, into)

    # --- before the loop --------------------------------------------------------------------
    def handshake(self, timeout_s: float | None = None) -> int:
        """Agree with the peer on the session; the wall-clock time (ns) to start at. Raises
        ``HandshakeError`` on a mismatch or when the peer does not appear in time, and
        ``KeyboardInterrupt`` / ``Terminated`` at once on a stop signal."""
        timeout_s = self.cfg.link.handshake_timeout_s if timeout_s is None else timeout_s
        session = self.transport.session
        mine = {"site": self.name, **shared_parts(self.cfg, self.n),
                "peer_timeout_ms": self.cfg.link.peer_timeout_ms}  # fmt: skip
        if self.side == HSI:
            mine["session_id"] = random.getrandbits(63) or 1
        heard: list[dict] = []  # the newest valid hello (a later one replaces it, never merges)
        past_ns = round(timeout_s * 1e9)
        ignored = self.hellos_ignored

        def on_hello(sample: Any) -> None:  # on Zenoh's thread: never raises
            try:
                hello = parse_hello(sample.payload.to_bytes(), past_ns)
            except Exception:  # noqa: BLE001 - whatever a stranger sends, never a traceback
                hello = "unreadable"
            if isinstance(hello, str):
                ignored[hello] = ignored.get(hello, 0) + 1
            elif hello["site"] == self.name:  # our own role: reflected, or a second site
                ignored["own_site"] = ignored.get("own_site", 0) + 1
            else:
                heard[:] = [hello]

        hello = session.declare_publisher(f"{self.base}/{self.name}/hello")
        listener = session.declare_subscriber(f"{self.base}/{self.peer}/hello", on_hello)
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                raise_if_stopped()
                hello.put(json.dumps(mine))
                theirs = heard[0] if heard else None
                if theirs is not None:
                    self._check_compatible(mine, theirs)
                    if self.side == HSI:
                        if "start_ns" not in mine:  # the TO is there: when both start
                            mine["start_ns"] = time.time_ns() + round(START_LEAD_S * 1e9)
                        elif (theirs.get("start_ns"), theirs.get("session_id")) == (
                            mine["start_ns"], mine["session_id"]
                        ):  # fmt: skip
                            break  # the TO has it
                    elif "start_ns" in theirs:
                        mine["session_id"] = theirs["session_id"]
                        mine["start_ns"] = theirs["start_ns"]
                        for _ in range(5):  # the HSI may miss one
                            hello.put(json.dumps(mine))
                            time.sleep(0.01)
                        break
                if time.monotonic() > deadline:
                    raise HandshakeError(
                        f"link: the {self.peer} site did not answer within {timeout_s:g} s "
                        f"(key {self.base}/{self.peer}, endpoints "
                        f"{self._endpoints_text()}){self.hellos_text()}"
                    )
                time.sleep(WAIT_SLICE_S)
        finally:
            listener.undeclare()
            hello.undeclare()
        self.connect(int(mine["session_id"]))
        return int(mine["start_ns"])

    def connect(self, session_id: int) -> None:
        """The session agreed: its receiver, the drift follower, and the subscription to the
        peer's packets (the handshake's last step; a loopback pair calls it directly)."""
        self.session_id = session_id
        self.receiver = Receiver(
            self.n, self.cfg.delay_ticks, session_id, 1 - self.side,
            policy=self.cfg.link.playout, arrivals=self._arrival_slots,
            delays=self._delay_capacity, codec=self.cfg.channel.codec != "none",
        )  # fmt: skip
        self.drift = DriftFollower(self.receiver.playout, self.cfg.link.max_drift_ppm)
        self.transport.listen(f"{self.base}/{self.peer}/waves", self._arrive)

    def hellos_text(self) -> str:
        """'; ignored N invalid hellos (reason n, ...)' or ''."""
        ignored = dict(self.hellos_ignored)
        if not ignored:
            return ""
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(ignored.items()))
        return f"; ignored {sum(ignored.values())} invalid hellos ({reasons})"

    def _check_compatible(self, mine: dict, theirs: dict) -> None:
        for key in ("wire_version", "joints", "rate_hz", "delay_ticks", "channel",
                    "peer_timeout_ms", "config_hash"):  # fmt: skip
            if theirs.get(key) != mine[key]:
                name = "link.peer_timeout_ms" if key == "peer_timeout_ms" else key
                if key == "channel" and isinstance(theirs.get(key), dict):
                    # name the setting (channel.codec, channel.deadband.weber_to, ...)
                    name, there, here = _first_difference(theirs[key], mine[key], "channel")
                    raise HandshakeError(
                        f"link: the {self.peer} site runs another session: {name} is "
                        f"{_short(there)} there, {here!r} here"
                    )
                raise HandshakeError(
                    f"link: the {self.peer} site runs another session: {name} is "
                    f"{_short(theirs.get(key))} there, {mine[key]!r} here"
                )

    def _endpoints_text(self) -> str:
        ends = getattr(self.cfg.link.zenoh, self.name)
        return ", ".join([*(f"listen {e}" for e in ends.listen),
                          *(f"connect {e}" for e in ends.connect)]) or "none"  # fmt: skip

    def start(self) -> None:
        """The loop starts now: the arrivals' times count in ticks of this site's clock from
        here, and the peer's silence from here plus the start-up grace."""
        self.start_ns = time.monotonic_ns()
        self.last_arrival_ns = self.start_ns + self.grace_ns
        self._last_receive_ns = 0  # the first tick's own gap is not counted (the grace's)

    # --- the Link interface -------------------------------------------------------------------
    def _arrive(self, data: bytes, now_ns: int | None = None) -> None:  # on Zenoh's thread
        """Bytes from the peer's key (``now_ns``: their instant, CLOCK_MONOTONIC; tests). One
        compiled call decodes them into the playout and notes their delay
        (``Receiver.arrive``); only the drift follower's few float operations stay in
        Python, and only for a fresh packet."""
        receiver = self.receiver
        if receiver is None:
            return
        with self._lock:  # the playout's kernels release the GIL: one thread at a time
            now = time.monotonic_ns() if now_ns is None else now_ns
            receiver.arrive(self._tick(), data, now)
            fresh = receiver.fresh
            # only an arrival that passed every check and was new to the playout tells where
            # the peer's clock is (replayed or duplicated copies would move the playout)
            if fresh and self.start_ns:
                ticks = (now - self.start_ns) / self.period_ns
                self.drift.arrival(ticks, receiver.decoder.seen_tick)  # type: ignore[union-attr]
        if fresh:
            self.last_arrival_ns = now
            self.heard = True

    def send(self, side: int, packet: Packet) -> None:
        self._packet = packet

    def receive(self, side: int, into: Packet) -> None:
        k = self._tick()
        now = time.monotonic_ns()
        # this site's own loop held off (SIGSTOP, a debugger, a starved CPU) longer than the
        # peer timeout left its robot unsupervised as a silent peer would: a stop, which says
        # so (the peer's packets may have arrived all along, queued: the silence below would
        # not fire, or blame the peer; with the codec it waits a maximum interval more)
        gap = now - self._last_receive_ns if self._last_receive_ns else 0
        self._last_receive_ns = now
        if gap > self.held_ns:
            raise SafetyStop(
                f"tick {k}: link: this site was held off for {gap / 1e6:.0f} ms between two "
                f"ticks (stopped or starved of CPU; link.peer_timeout_ms = "
                f"{self.cfg.link.peer_timeout_ms:g}): its robot went unsupervised"
            )
        silent = now - self.last_arrival_ns
        if silent > self.timeout_ns:
            since = "" if self.heard else " since the start"
            silent += 0 if self.heard else self.grace_ns
            raise SafetyStop(
                f"tick {k}: link: nothing from the {self.peer} site{since} for "
                f"{silent / 1e6:.0f} ms (link.peer_timeout_ms = "
                f"{self.cfg.link.peer_timeout_ms:g}{self._codec_text()})"
            )
        with self._lock:
            used = self.receiver.take(k, into)  # type: ignore[union-attr]  # (made by connect)
            if self.arrival is not None:
                self._note_arrival(self.arrival, used, into.tick)

    def _codec_text(self) -> str:
        """', after the codec's maximum interval of N ticks' or ''."""
        ch = self.cfg.channel
        if ch.codec == "none":
            return ""
        return f", after the codec's maximum interval of {ch.deadband.max_interval_ticks} ticks"

    def _note_arrival(self, a: Arrival, used: int, s: int) -> None:
        arrived = self.receiver.arrived  # type: ignore[union-attr]  # (made by connect)
        row = arrived[s % len(arrived)]
        if not used:
            a.none()
        elif row[0] == s:
            a.sender_tick, a.arrival_tick = s, row[1]
            a.one_way_delay_us, a.valid = row[2] / 1e3, 1.0
        else:  # (a packet is stored only after it was noted: not reached)
            a.sender_tick, a.valid = s, 1.0
            a.arrival_tick, a.one_way_delay_us = -1.0, math.nan

    def end_tick(self, side: int) -> None:
        packet = self._packet
        assert packet is not None  # (attach() gave the packet before the first tick)
        if packet.unsent:  # the codec sends nothing: no put, nothing for Zenoh to do
            self.not_sent += 1
            return
        now = time.monotonic_ns()
        # numbered by the packets sent: the peer counts a loss by a jump of the number
        data = encode_into(self._wire, packet, self.session_id, now, self.side, self.sent)
        impairment = self.impairment
        if impairment is None:
            self.transport.send(data, now)
        else:  # each surviving copy to the sender thread, with its instant
            delays = impairment.delays_ms
            for k in range(impairment.decide(packet.tick)):
                self.transport.send_at(data, now + int(delays[k] * 1e6))
        self.sent += 1

    # --- afterwards -----------------------------------------------------------------------------
    def silence(self, ticks: int) -> str | None:
        """Why a run of ``ticks`` did not really run with its peer, or None: it used fewer than
        ``SILENT_FRACTION`` of the peer's packets due (those sent after the start-up grace and
        the playout delay); a peer timeout longer than the run never fires, this does."""
        if self.receiver is None:
            return None
        grace_ticks = round(max(self.timeout_ns, STARTUP_GRACE_S * 1e9) / (self.cfg.dt * 1e9))
        due = ticks - self.cfg.delay_ticks - grace_ticks
        if self.cfg.channel.codec != "none":  # a live codec sends once a maximum interval
            due //= self.cfg.channel.deadband.max_interval_ticks
        used = self.receiver.playout.counters()["used"]
        if due <= 0 or used >= SILENT_FRACTION * due:
            return None
        return (
            f"link: the {self.peer} site was silent: {used} of its {due} packets due were "
            f"used here (fewer than {SILENT_FRACTION:.0%})"
        )

    def stats(self) -> dict:
        """What the link did: this site's packets sent, and the peer's as received here."""
        received = self.receiver.stats() if self.receiver is not None else {}
        r = self.receiver
        d = r.delays_ns[: r.delay_count] / 1e3 if r is not None else np.zeros(0)
        delay_us = (
            {"min": float(d.min()), "p50": float(np.percentile(d, 50)),
             "p99": float(np.percentile(d, 99)), "max": float(d.max())} if d.size else None
        )  # fmt: skip
        out = {
            "sent": self.sent,
            "one_way_delay_us": delay_us,
            "send_errors": self.transport.send_errors,
            # how long after its stamp (or its instant, when held) each packet's put began,
            # and how long the put took (on the tick, without a hold)
            "send_after_due_us": self.transport.late_out_us(),
            "put_us": self.transport.put_us(),
            "from_peer": received,
        }
        if self.cfg.channel.codec != "none":  # ticks its codec sent nothing
            out["not_sent"] = self.not_sent
        if self.drift is not None:
            out["drift"] = self.drift.stats()
        if self.hellos_ignored:  # what strangers said during the handshake
            out["hellos_ignored"] = dict(self.hellos_ignored)
        imp = self.impairment
        if imp is not None:  # what this site's impairment stage did to its own packets
            out["impairment"] = {"decided": imp.decided, "lost": imp.lost,
                                 "duplicated": imp.duplicated, "reordered": imp.reordered,
                                 **self.transport.hold_stats()}  # fmt: skip
        return out

    def close(self) -> None:
        self.transport.close()
