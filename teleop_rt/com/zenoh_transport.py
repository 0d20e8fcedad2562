"""Eclipse Zenoh as the transport between two sites: one Zenoh session per site, in peer mode
with multicast scouting off and explicit endpoints, a publisher of this site's packets and a
subscriber to the peer's (``teleop_rt.com.zenoh_link`` puts packets on it).

Why these settings (docs/network.md has the figures measured here): each packet is
worth something only while it is fresh, so it is sent at once (``express``: no batching), at
``Priority.REAL_TIME``, and dropped rather than queued when the link is congested
(``CongestionControl.DROP``); a UDP link by default, since over TCP one stalled segment delays
every later sample (head-of-line blocking), and a wave that arrives late is worth less than one
that is lost (the receiver's playout rule replaces it with a passive zero).

The tick publishes its packet itself (``send``): zenoh-python's ``put`` copies the bytes into
Zenoh's real-time queue and wakes Zenoh's transmit thread, which writes the socket; it never
waits (``CongestionControl.DROP`` with ``WAIT_BEFORE_DROP_US`` 0: a full queue drops the packet
at once, where Zenoh's default waits up to 1 ms for room) and does no network I/O. Measured on
the tick (docs/network.md): 13-18 us at p50, p99.9 40-100 us, max 0.1-0.8 ms on this loaded VM
(a preemption of the loop's CPU, as any tick can have). A sender thread woken by the tick, as
before, cost more in the tick than the put: it runs at a priority above the loop's (else it
waits for the tick and Zenoh's threads), so it preempted the tick at the hand-over and again
when a compiled kernel released the GIL, and did its put inside the tick anyway (the tick's
compiled ``site_after_models`` took 21 us at p50 in real time against 0.8 in fast mode).
Received bytes go to ``listen``'s callback on Zenoh's thread.

Zenoh's own threads (runtime, transmit, receive: ``raise_zenoh_threads``) run at a real-time
priority below the loop's: at normal priority on a loaded host they waited behind other
processes (one-way p99 3.3 ms, 25-30 % of the packets late at D = 1 tick, peer-timeout stops;
at SCHED_FIFO 70: p99 0.3 ms, 0.1 %).

Zenoh's queue of real-time batches holds ``TX_QUEUE_BATCHES`` instead of its default 2: with
``express`` every packet is a batch, and when Zenoh's own transmit thread (normal priority, on
the CPU of the site's real-time threads) was held off for two ticks, the next packets waited
and were dropped (0.7 % of them in a 30 s run on this loaded VM, 0.03 % with 16).

With a ``hold`` (``teleop_rt.com.hold``: the impairment stage in front of Zenoh) the tick
``send_at``s each copy of its packet with the instant it is due instead, and a sender thread
(woken by a bare lock) sleeps until the earliest due instant and publishes what is due, in due
order. Every put records how long after it was due (its stamp, or its instant) it began (10 us
bins) and how long it took (1 us bins).
"""

from __future__ import annotations

import json
import os
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from teleop_rt.com.hold import NEVER, HeldPackets
from teleop_rt.errors import TeleopError

TX_QUEUE_BATCHES = 16  # Zenoh's real-time transmit queue, batches (one packet each: express)

# Zenoh waits this long for room in a full queue before it drops a DROP packet (its default
# 1000 us would hold the tick that publishes): 0, a full queue drops the packet at once
WAIT_BEFORE_DROP_US = 0

BIN_NS = 10_000  # the histogram of how late packets went out: 10 us bins, the last "or later"
BINS = 1000
PUT_BINS = 10_000  # the histogram of how long a put took: 1 us bins, the last "or longer"


class TransportError(TeleopError):
    """The transport cannot be set up (bad endpoint, certificates, port in use)."""

    exit_code = 2


# where in Zenoh's Rust source an error was raised: " at /root/.cargo/.../unicast.rs:418."
_SOURCE_PLACE = re.compile(r"\s+at \S+\.rs:\d+\.?")
_IN_USE = ("Address already in use", "os error 98")
_ENDPOINT = re.compile(r"^(?P<proto>[a-z0-9-]+)/(?P<addr>.*):(?P<port>\d+)(?P<rest>[#?].*)?$")


def open_failure(err: object, listen: list[str], key: str) -> str:
    """One line for a Zenoh session that would not open: for an address in use, the endpoint
    and the ``--set`` that moves it (``key``: the config key of the ``listen`` list);
    otherwise Zenoh's words without its source file places."""
    text = _SOURCE_PLACE.sub("", str(err)).strip()
    if any(mark in text for mark in _IN_USE):
        named = [e for e in listen if e in text] or listen[:1]
        if named:
            at = named[0]
            m = _ENDPOINT.match(at)
            other = (f"{m['proto']}/{m['addr']}:{int(m['port']) + 1}{m['rest'] or ''}"
                     if m and int(m["port"]) < 65535 else "PROTO/HOST:PORT")  # fmt: skip
            return (f"{key}: {at} is in use (another session or program listens there); give "
                    f"this site another, e.g. --set {key}=[{other}], and the peer's connect "
                    "the same")  # fmt: skip
    return f"link: cannot open the Zenoh session ({text})"


def zenoh_config(
    listen: list[str],
    connect: list[str],
    tls: dict[str, Path] | None = None,
    mode: str = "peer",
    acl: dict | None = None,
) -> Any:
    """A Zenoh config: ``mode`` (peer, or client of a router), no scouting, these endpoints;
    with ``tls`` (root_ca, certificate, private_key) mutual TLS on tls/ endpoints; ``acl``:
    Zenoh's ``access_control`` section (``zenoh_link.role_acl``)."""
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    c.insert_json5("transport/link/tx/queue/size/real_time", str(TX_QUEUE_BATCHES))
    c.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop",
                   str(WAIT_BEFORE_DROP_US))  # fmt: skip
    if tls:
        link = {
            "root_ca_certificate": str(tls["root_ca"]),
            "enable_mtls": True,
            "listen_private_key": str(tls["private_key"]),
            "listen_certificate": str(tls["certificate"]),
            "connect_private_key": str(tls["private_key"]),
            "connect_certificate": str(tls["certificate"]),
        }
        c.insert_json5("transport/link/tls", json.dumps(link))
    if acl:
        c.insert_json5("access_control", json.dumps(acl))
    return c


def publisher_qos() -> dict[str, Any]:
    """How a site publishes its packets (``declare_publisher``'s keywords): at once, no
    batching (``express``), at ``Priority.REAL_TIME``, dropped rather than queued when the link
    is congested (``CongestionControl.DROP``)."""
    import zenoh

    return {"congestion_control": zenoh.CongestionControl.DROP,
            "priority": zenoh.Priority.REAL_TIME, "express": True}  # fmt: skip


class ZenohTransport:
    """One site's Zenoh session: ``send`` bytes on ``key_out`` (a ``put`` that never waits),
    ``listen`` to a peer's key; ``session`` serves the handshake too."""

    def __init__(
        self,
        config: Any,
        key_out: str,
        packet_bytes: int = 0,
        hold: HeldPackets | None = None,
        listen: tuple[list[str], str] = ([], "link.zenoh listen"),
    ) -> None:
        """``packet_bytes``: a packet's size (``send`` copies it into a buffer of that size);
        ``hold``: where ``send_at`` keeps packets until they are due, published by a sender
        thread (None: no hold, no thread); ``listen``: the config's listen endpoints and their
        key, for an endpoint in use."""
        import zenoh

        try:
            self.session = zenoh.open(config)
        except Exception as err:  # zenoh raises ZError for bad endpoints, ports in use, TLS
            raise TransportError(open_failure(err, *listen)) from None
        self.publisher = self.session.declare_publisher(key_out, **publisher_qos())
        self.subscribers: list[Any] = []
        self.sent = self.send_errors = 0
        self.hold = hold
        self.late_out = np.zeros(BINS, dtype=np.int64)  # put instant - due instant, by bin
        self.late_out_max_ns = 0
        self.put_ns = np.zeros(PUT_BINS, dtype=np.int64)  # how long each put took, by 1 us
        self.put_max_ns = 0
        self._out = bytearray(packet_bytes)  # what send gives Zenoh: the tick's packet, copied
        self._running = True
        self._thread: threading.Thread | None = None
        if hold is not None:  # held packets go out at their instants, from a thread
            self._lock = threading.Lock()
            self._wake = threading.Lock()  # held: nothing new; released by the tick to wake
            self._wake.acquire()
            self._until = 0  # the due instant the sender sleeps until (NEVER: until woken)
            self._priority: int | None = None  # SCHED_FIFO priority the sender should take
            self._thread = threading.Thread(target=self._sender, name="teleop-rt-send",
                                            daemon=True)  # fmt: skip
            self._thread.start()

    def listen(self, key: str, on_bytes: Callable[[bytes], None]) -> None:
        """Call ``on_bytes`` with every payload published on ``key`` (on Zenoh's thread)."""

        def received(sample: Any) -> None:
            on_bytes(sample.payload.to_bytes())

        self.subscribers.append(self.session.declare_subscriber(key, received))

    def send(self, data: bytes | bytearray | memoryview, at_ns: int) -> None:
        """Publish this tick's packet now, from the caller's thread (the tick). The ``put``
        never waits: Zenoh copies the bytes into its real-time queue and wakes its transmit
        thread, which writes the socket; a full queue drops the packet at once
        (``CongestionControl.DROP``, ``WAIT_BEFORE_DROP_US``). ``at_ns``: when the packet was
        stamped (CLOCK_MONOTONIC)."""
        out = self._out
        out[:] = data  # (zenoh-python takes bytes or a bytearray; same size: no allocation)
        self._put(out, at_ns)

    def send_at(self, data: bytes | bytearray | memoryview, due_ns: int) -> None:
        """Hold a copy of ``data`` until ``due_ns`` (CLOCK_MONOTONIC), then publish it from the
        sender thread (never blocks; a full hold drops the packet and counts it ``overflow``)."""
        with self._lock:
            self.hold.put(due_ns, data)  # type: ignore[union-attr]
            wake = due_ns < self._until  # the sender sleeps past it (else: no wake-up needed)
        if wake:
            self._signal()

    def _signal(self) -> None:
        try:
            self._wake.release()
        except RuntimeError:
            pass  # released already: the sender has not yet woken for the last one

    def raise_priority(self, priority: int) -> None:
        """Run the sender thread (if there is one) at SCHED_FIFO ``priority``, above a
        real-time loop's, so that a held packet goes out at its instant, not after other
        threads of the CPU."""
        if self._thread is not None:
            self._priority = priority

    def raise_zenoh_threads(self, priority: int) -> list[str]:
        """Run Zenoh's own threads (its runtime, transmit and receive threads, which also run
        the receive callback) at SCHED_FIFO ``priority``: below a real-time loop's, so that they
        never hold a tick, and above every normal process of the CPU, so that a loaded host
        does not hold a packet. Python's threads (named ``python``) are left alone. Returns
        the threads raised (their names); none where the OS refuses."""
        raised = []
        for tid in os.listdir("/proc/self/task"):
            try:
                name = Path(f"/proc/self/task/{tid}/comm").read_text().strip()
                if name.startswith("python"):
                    continue
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
                raised.append(name)
            except OSError:
                continue  # (a thread that ended, or not granted)
        return sorted(raised)

    def _sender(self) -> None:
        hold = self.hold
        assert hold is not None  # (the thread runs only with a hold)
        while self._running:
            with self._lock:
                _, due = hold.next_due()
                self._until = due
            timeout = None if due == NEVER else (due - time.monotonic_ns()) / 1e9
            if timeout is None or timeout > 0:
                self._wake.acquire(timeout=-1 if timeout is None else timeout)
            self._until = 0  # awake: it looks at the hold again before it sleeps
            if self._priority is not None:  # applied by the thread to itself
                try:
                    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self._priority))
                except OSError:
                    pass  # not granted: the loop's notes say what was
                self._priority = None
            self._publish_due()

    def _put(self, payload: bytes | bytearray | memoryview, due_ns: int) -> None:
        start = time.monotonic_ns()
        late = start - due_ns
        self.late_out[min(max(late, 0) // BIN_NS, BINS - 1)] += 1
        self.late_out_max_ns = max(self.late_out_max_ns, late)
        try:
            self.publisher.put(payload)
            self.sent += 1
        except Exception:  # a closed session while stopping; counted, never raised
            self.send_errors += 1
        took = time.monotonic_ns() - start
        self.put_ns[min(took // 1000, PUT_BINS - 1)] += 1
        self.put_max_ns = max(self.put_max_ns, took)

    def _publish_due(self) -> None:
        """Publish every held packet whose instant has come, earliest first."""
        hold = self.hold
        while self._running:
            with self._lock:
                slot, due = hold.next_due()  # type: ignore[union-attr]
                now = time.monotonic_ns()
                if due > now:
                    return
                payload = hold.pop(slot)  # type: ignore[union-attr]
            self._put(payload, due)

    def put_us(self) -> dict | None:
        """How long a ``put`` took, us: p50, p99, p99.9 (upper edges of 1 us bins), the exact
        max; None before the first."""
        return _percentiles(self.put_ns, 1000, self.put_max_ns, (0.5, 0.99, 0.999))

    def late_out_us(self) -> dict | None:
        """How long after it was due a packet's put began, us: p50, p99 (upper edges of 10 us
        bins), the exact max; None before the first."""
        return _percentiles(self.late_out, BIN_NS, self.late_out_max_ns, (0.5, 0.99))

    def hold_stats(self) -> dict:
        """What the hold did: packets held, published after their hold, still held at the end,
        refused (a full hold)."""
        hold = self.hold
        if hold is None:
            return {}
        published = hold.held - len(hold)
        return {"held": hold.held, "published": published, "unsent": len(hold),
                "overflow": hold.overflow}  # fmt: skip

    def close(self) -> None:
        """Stop the sender (if any) and close the session (idempotent)."""
        if not self._running:
            return
        self._running = False
        if self._thread is not None:
            self._signal()
            self._thread.join(1.0)
        for thing in (*self.subscribers, self.publisher):
            try:
                thing.undeclare()
            except Exception:
                pass
        self.session.close()


def _percentiles(hist: np.ndarray, bin_ns: int, max_ns: int, qs: tuple) -> dict | None:
    """Percentiles (upper bin edges, us) of a histogram of ``bin_ns`` bins, and the max."""
    total = int(hist.sum())
    if not total:
        return None
    cumulative = np.cumsum(hist)
    names = {0.5: "p50", 0.99: "p99", 0.999: "p99.9"}
    out = {names[q]: (int(np.searchsorted(cumulative, q * total)) + 1) * bin_ns / 1e3 for q in qs}
    return {**out, "max": max_ns / 1e3}
