"""One peer of the link's floors, for tools/bench_link.py: a process that sends a packet of a
site's size every tick (1 kHz, absolute deadlines, the loop's real-time grant) and receives its
peer's, over raw UDP from Python or over bare zenoh-python with the project's settings (the
same ``zenoh_config``, ``publisher_qos`` and queue as a site's link), nothing else.

    python tools/link_floor.py udp|zenoh hsi|to --port P --start NS [--seconds S] [--every K]

Each packet carries its sequence number and its send instant (CLOCK_MONOTONIC); the receiver
(Python code on the receiving thread: Zenoh's callback, or a thread blocked in ``recv_into``)
records its one-way delay. Both peers start their ticks at the wall-clock instant ``--start``
(as two sites do after their handshake); counted are the packets sent after ``WARM_S`` for
``--seconds``; ``--every K`` sends on every Kth tick only (a codec's sparse packets). Prints
one JSON line: the delays' p50 / p99 / max (us), received, lost, late (delay over a tick) and
the process's CPU per tick over the counted window.
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt.com.wire import wire_size  # noqa: E402
from teleop_rt.com.zenoh_transport import publisher_qos, zenoh_config  # noqa: E402
from teleop_rt.loop import acquire_realtime  # noqa: E402

PERIOD_NS = 1_000_000
WARM_S = 0.5  # the first ticks are not counted (the peers' connection settles)
TAIL_S = 0.2  # the peer's last counted packets arrive within this
JOINTS = 2  # the paper experiment's: the packet a site sends is wire_size(2) bytes
STAMP = struct.Struct("<qq")  # sequence number (tick), send instant ns


class Received:
    """The peer's packets, by sequence number (preallocated)."""

    def __init__(self, first: int, count: int) -> None:
        self.first, self.count = first, count
        self.delay_ns = np.full(count, -1, dtype=np.int64)

    def arrive(self, data: bytes | bytearray | memoryview) -> None:
        seq, sent = STAMP.unpack_from(data)
        k = seq - self.first
        if 0 <= k < self.count and self.delay_ns[k] < 0:
            self.delay_ns[k] = time.monotonic_ns() - sent


def main() -> int:
    p = argparse.ArgumentParser(description="one peer of tools/bench_link.py's floors")
    p.add_argument("kind", choices=("udp", "zenoh"))
    p.add_argument("site", choices=("hsi", "to"))
    p.add_argument("--port", type=int, required=True, help="the HSI's port (the TO's: P + 1)")
    p.add_argument("--start", type=int, required=True, help="wall-clock instant (ns) to start at")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--every", type=int, default=1, help="send on every Kth tick (default 1)")
    args = p.parse_args()
    warm, ticks = round(WARM_S * 1000), round(args.seconds * 1000)
    total = warm + ticks + round(TAIL_S * 1000)
    received = Received(warm, ticks)
    payload = bytearray(wire_size(JOINTS))
    me, peer = (args.port, args.port + 1) if args.site == "hsi" else (args.port + 1, args.port)
    if args.kind == "udp":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", me))
        to = ("127.0.0.1", peer)

        def listen() -> None:
            buf = bytearray(len(payload))
            while True:
                n = sock.recv_into(buf)
                if n == len(buf):
                    received.arrive(buf)

        threading.Thread(target=listen, daemon=True).start()

        def send(data: bytearray) -> None:
            sock.sendto(data, to)
    else:
        at = f"udp/127.0.0.1:{args.port}"
        listen_on, connect_to = ([at], []) if args.site == "hsi" else ([], [at])
        import zenoh

        session = zenoh.open(zenoh_config(listen_on, connect_to))
        other = "to" if args.site == "hsi" else "hsi"
        publisher = session.declare_publisher(f"floor/{args.site}", **publisher_qos())
        session.declare_subscriber(f"floor/{other}",
                                   lambda s: received.arrive(s.payload.to_bytes()))  # fmt: skip

        def send(data: bytearray) -> None:
            publisher.put(data)

    grant = acquire_realtime(cpu=None)  # SCHED_FIFO, memory locked, as a site's loop
    while (left := args.start - time.time_ns()) > 0:
        time.sleep(min(left / 1e9, 0.02))
    deadline = time.monotonic_ns()
    cpu0 = cpu1 = 0.0
    for k in range(total):
        deadline += PERIOD_NS
        left = deadline - time.monotonic_ns()
        if left > 0:
            time.sleep(left / 1e9)
        if k == warm:
            cpu0 = time.process_time()
        elif k == warm + ticks:
            cpu1 = time.process_time()
        if k % args.every == 0:
            STAMP.pack_into(payload, 0, k, time.monotonic_ns())
            send(payload)
    grant.release()
    d = received.delay_ns[(-warm) % args.every :: args.every]  # the ticks it sent on
    got = d[d >= 0] / 1e3
    due = d.size
    out = {
        "kind": args.kind,
        "site": args.site,
        "every": args.every,
        "due": int(due),
        "received": int(got.size),
        "lost": int(due - got.size),
        "late": int(np.count_nonzero(got > PERIOD_NS / 1e3)),
        "one_way_us": {
            "p50": float(np.percentile(got, 50)),
            "p99": float(np.percentile(got, 99)),
            "max": float(got.max()),
        }
        if got.size
        else None,  # fmt: skip
        "cpu_us_per_tick": 1e6 * (cpu1 - cpu0) / ticks,
    }
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
