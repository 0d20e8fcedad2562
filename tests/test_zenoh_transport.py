"""The transport under a site's link (issue 27): without an impairment the tick's ``send`` is
the put itself (no sender thread, nothing left for a thread to do when it returns), the put
never waits for room in Zenoh's queue, and Zenoh's own threads (not Python's) are the ones
raised to a real-time priority below the loop's."""

from __future__ import annotations

import os
import threading
import time

import pytest

from teleop_rt.com.wire import wire_size
from teleop_rt.com.zenoh_transport import WAIT_BEFORE_DROP_US, ZenohTransport, zenoh_config
from tests.test_zenoh_sites import free_port

pytest.importorskip("zenoh")


def pair() -> tuple[ZenohTransport, ZenohTransport, list[bytes]]:
    """Two transports joined on loopback; what the second received."""
    at = f"udp/127.0.0.1:{free_port()}"
    size = wire_size(2)
    a = ZenohTransport(zenoh_config([at], []), "t27/a", size)
    b = ZenohTransport(zenoh_config([], [at]), "t27/b", size)
    got: list[bytes] = []
    b.listen("t27/a", got.append)
    return a, b, got


def test_send_is_the_put_and_no_thread_waits_behind_it() -> None:
    a, b, got = pair()
    try:
        assert a._thread is None  # no sender thread
        assert "teleop-rt-send" not in {t.name for t in threading.enumerate()}
        payload = bytes(range(wire_size(2)))
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:  # (until the subscriber is matched)
            a.send(payload, time.monotonic_ns())
            # the put is done when send returns: counted, and its duration recorded
            assert a.sent == int(a.put_ns.sum()) and a.send_errors == 0
            time.sleep(0.01)
        assert got and got[0] == payload
        put = a.put_us()
        assert put is not None and put["p50"] <= put["p99"] <= put["p99.9"]
    finally:
        a.close()
        b.close()


def test_a_full_queue_drops_at_once() -> None:
    """Zenoh's default waits up to 1 ms for room before it drops a DROP packet; the tick's put
    must not: the config the transport opens with says 0."""
    c = zenoh_config([], [])
    assert WAIT_BEFORE_DROP_US == 0
    assert '"wait_before_drop":0' in c.get_json("transport/link/tx/queue/congestion_control")


def test_only_zenohs_threads_are_raised() -> None:
    a, b, _ = pair()
    try:
        raised = a.raise_zenoh_threads(1)
        if not raised:
            pytest.skip("SCHED_FIFO not granted here")
        assert not any(name.startswith("python") for name in raised)
        assert os.sched_getscheduler(0) != os.SCHED_FIFO  # the calling thread left alone
        fifo = []
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/comm") as f:
                    name = f.read().strip()
                if os.sched_getscheduler(int(tid)) == os.SCHED_FIFO:
                    fifo.append(name)
            except OSError:
                continue
        assert sorted(fifo) == raised
    finally:
        a.close()
        b.close()
