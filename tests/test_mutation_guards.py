"""Guards that survived mutation before (issue 25): each test here fails when its guard is
broken as the issue describes."""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.com.channel import ChannelMonitor, monitor_step
from teleop_rt.com.port import EFFORT, FLOW


def _port(n: int, flow: float, effort: float) -> np.ndarray:
    f = np.zeros((max(FLOW, EFFORT) + 1) * n)
    f[FLOW * n : (FLOW + 1) * n] = flow
    f[EFFORT * n : (EFFORT + 1) * n] = effort
    return f


def test_a_nan_channel_never_looks_passive() -> None:
    """The running minimum of the channel energy takes a NaN total as a new minimum, and keeps
    it (``not total >= min``; ``total < min`` would keep the last finite minimum, and a
    diverged channel would pass the passivity check)."""
    n, dt = 2, 1e-3
    monitor = ChannelMonitor(n, dt)
    quiet = _port(n, 0.0, 0.0)
    monitor_step(monitor.f, n, _port(n, 1.0, 2.0), quiet)  # 2 W per joint for a tick
    assert math.isclose(monitor.total_energy, 2 * 2.0 * dt, rel_tol=1e-12)
    assert monitor.min_total_energy == 0.0  # the start's 0 J stays the minimum
    monitor_step(monitor.f, n, _port(n, math.nan, 2.0), quiet)
    assert math.isnan(monitor.total_energy)
    assert math.isnan(monitor.min_total_energy)
    monitor_step(monitor.f, n, _port(n, 1.0, 2.0), quiet)  # NaN energy stays NaN
    assert math.isnan(monitor.min_total_energy)


def test_a_reordered_packet_never_lowers_the_peers_e_in_at_the_port() -> None:
    """TDPA's bound uses the peer's E_in, monotone at the sender: an older packet used after a
    newer one (reordered) must not lower it (``max(PEER_E_IN, rx)``; taking ``rx`` would give
    the port back energy the peer already accounted)."""
    from teleop_rt.com.channel import make_port
    from teleop_rt.com.port import HSI, Packet, port_step

    n = 2
    port = make_port(HSI, "tdpa", [1.5] * n, 1, 1e-3, None, "bounded")
    rx, tx = Packet(n), Packet(n)
    for e_in, tick in ((5.0, 7), (3.0, 4)):  # the newer packet first, then an older one
        rx.e_in[:] = e_in
        rx.tick = rx.seq = tick
        rx.valid = 1
        port_step(port.f, port.i, n, rx.f, rx.i, tx.f)
    assert np.array_equal(port.peer_e_in, [5.0, 5.0])
