"""Eclipse Zenoh as the transport between two sites: one Zenoh session per site, in peer mode
with multicast scouting off and explicit endpoints, a publisher of this site's packets and a
subscriber to the peer's (``teleop_rt.com.zenoh_link`` puts packets on it).

Why these settings (docs/network.md has the figures measured here): each packet is
worth something only while it is fresh, so it is sent at once (``express``: no batching), at
``Priority.REAL_TIME``, and dropped rather than queued when the link is congested
(``CongestionControl.DROP``); a UDP link by default, since over TCP one stalled segment delays
every later sample (head-of-line blocking), and a wave that arrives late is worth less than one
that is lost (the receiver's playout rule replaces it with a passive zero).

Nothing here runs on the tick: ``send`` copies the bytes into a one-slot mailbox and wakes a
sender thread, which publishes while the loop sleeps to its next deadline (a ``put`` took 26 us
at p50 and over a millisecond at p99 on this VM); a packet that the sender has not taken by
the next tick is replaced and counted. The wake-up is a bare lock released by the tick and
acquired by the sender (a ``threading.Event`` cycle cost about 16 us more CPU here). Received
bytes go to ``listen``'s callback on Zenoh's thread.

Zenoh's queue of real-time batches holds ``TX_QUEUE_BATCHES`` instead of its default 2: with
``express`` every packet is a batch, and when Zenoh's own transmit thread (normal priority, on
the CPU of the site's real-time threads) was held off for two ticks, the next packets waited
and were dropped (0.7 % of them in a 30 s run on this loaded VM, 0.03 % with 16).

With a ``hold`` (``teleop_rt.com.hold``: the impairment stage in front of Zenoh) the tick
``send_at``s each copy of its packet with the instant it is due instead; the sender thread
sleeps until the earliest due instant (or the next packet) and publishes what is due, in due
order. Either way the sender records how long after it was due (handed over, or its instant)
each packet went out (10 us bins): the sending site's part of the one-way delay.
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

BIN_NS = 10_000  # the histogram of how late packets went out: 10 us bins, the last "or later"
BINS = 1000


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


class ZenohTransport:
    """One site's Zenoh session: ``send`` bytes on ``key_out`` (off the tick), ``listen`` to a
    peer's key; ``session`` serves the handshake too."""

    def __init__(
        self,
        config: Any,
        key_out: str,
        max_bytes: int = 4096,
        hold: HeldPackets | None = None,
        listen: tuple[list[str], str] = ([], "link.zenoh listen"),
    ) -> None:
        """``hold``: where ``send_at`` keeps packets until they are due (None: no hold);
        ``listen``: the config's listen endpoints and their key, for an endpoint in use."""
        import zenoh

        try:
            self.session = zenoh.open(config)
        except Exception as err:  # zenoh raises ZError for bad endpoints, ports in use, TLS
            raise TransportError(open_failure(err, *listen)) from None
        self.publisher = self.session.declare_publisher(
            key_out,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME,
            express=True,
        )
        self.subscribers: list[Any] = []
        # the mailbox: one slot, written by the tick, taken by the sender thread
        self._slot = bytearray(max_bytes)
        self._size = 0
        self._fresh = False
        self._lock = threading.Lock()
        self._wake = threading.Lock()  # held: nothing new; released by the tick to wake
        self._wake.acquire()
        self._running = True
        self.sent = self.replaced = self.send_errors = 0
        self.hold = hold
        self.late_out = np.zeros(BINS, dtype=np.int64)  # put instant - due instant, by bin
        self.late_out_max_ns = 0
        self._at = 0  # when the mailbox's packet was handed over (CLOCK_MONOTONIC ns)
        self._until = 0  # the due instant the sender sleeps until (NEVER: until woken)
        self._priority: int | None = None  # SCHED_FIFO priority the sender should take
        self._thread = threading.Thread(target=self._sender, name="teleop-rt-send", daemon=True)
        self._thread.start()

    def listen(self, key: str, on_bytes: Callable[[bytes], None]) -> None:
        """Call ``on_bytes`` with every payload published on ``key`` (on Zenoh's thread)."""

        def received(sample: Any) -> None:
            on_bytes(sample.payload.to_bytes())

        self.subscribers.append(self.session.declare_subscriber(key, received))

    def send(self, data: bytes | bytearray | memoryview, at_ns: int) -> None:
        """Hand this tick's packet to the sender at ``at_ns`` (CLOCK_MONOTONIC; never blocks
        on the network)."""
        n = len(data)
        with self._lock:
            if self._fresh:
                self.replaced += 1  # the sender did not take the last one in time
            self._slot[:n] = data
            self._size = n
            self._at = at_ns
            self._fresh = True
        self._signal()

    def send_at(self, data: bytes | bytearray | memoryview, due_ns: int) -> None:
        """Hold a copy of ``data`` until ``due_ns`` (CLOCK_MONOTONIC), then publish it (never
        blocks; a full hold drops the packet and counts it ``overflow``)."""
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
        """Run the sender at SCHED_FIFO ``priority`` (above a real-time loop's, so that a
        packet goes out while the loop sleeps, not after other threads of the CPU)."""
        self._priority = priority

    def _sender(self) -> None:
        while self._running:
            timeout = None
            if self.hold is not None:
                with self._lock:
                    _, due = self.hold.next_due()
                    self._until = due
                if due != NEVER:
                    timeout = (due - time.monotonic_ns()) / 1e9
            if timeout is None or timeout > 0:
                self._wake.acquire(timeout=-1 if timeout is None else timeout)
            self._until = 0  # awake: it looks at the hold again before it sleeps
            if self._priority is not None:  # applied by the thread to itself
                try:
                    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self._priority))
                except OSError:
                    pass  # not granted: the loop's notes say what was
                self._priority = None
            if self.hold is not None:
                self._publish_due()
            with self._lock:
                if not self._fresh:
                    continue
                payload = bytes(self._slot[: self._size])
                due = self._at
                self._fresh = False
            self._put(payload, due)

    def _put(self, payload: bytes, due_ns: int) -> None:
        late = time.monotonic_ns() - due_ns
        self.late_out[min(max(late, 0) // BIN_NS, BINS - 1)] += 1
        self.late_out_max_ns = max(self.late_out_max_ns, late)
        try:
            self.publisher.put(payload)
            self.sent += 1
        except Exception:  # a closed session while stopping; counted, never raised
            self.send_errors += 1

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

    def late_out_us(self) -> dict | None:
        """How long after it was due a packet went out, us: p50, p99 (upper edges of 10 us
        bins), the exact max; None before the first."""
        total = int(self.late_out.sum())
        if not total:
            return None
        cumulative = np.cumsum(self.late_out)
        p50, p99 = (int(np.searchsorted(cumulative, q * total)) for q in (0.5, 0.99))
        return {"p50": (p50 + 1) * BIN_NS / 1e3, "p99": (p99 + 1) * BIN_NS / 1e3,
                "max": self.late_out_max_ns / 1e3}  # fmt: skip

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
        """Stop the sender and close the session (idempotent)."""
        if not self._running:
            return
        self._running = False
        self._signal()
        self._thread.join(1.0)
        for thing in (*self.subscribers, self.publisher):
            try:
                thing.undeclare()
            except Exception:
                pass
        self.session.close()
