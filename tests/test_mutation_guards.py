"""Guards that survived mutation before (issue 25): each test here fails when its guard is
broken as the issue describes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop_rt.com.channel import ChannelMonitor, monitor_step
from teleop_rt.com.port import Port
from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"


def _port(n: int, flow: float, effort: float) -> np.ndarray:
    Pt = Port.idx
    f = np.zeros((max(Pt.FLOW, Pt.EFFORT) + 1) * n)
    f[Pt.FLOW * n : (Pt.FLOW + 1) * n] = flow
    f[Pt.EFFORT * n : (Pt.EFFORT + 1) * n] = effort
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


@pytest.mark.parametrize(
    "spec",
    [{"enabled": False}, {"enabled": False, "torque_limits": "off"}, {"torque_limits": "off"},
     {}, {"torque_limits": "stop"}],
    ids=["safety-off", "safety-off-limits-off", "limits-off", "saturate", "stop"],
)  # fmt: skip
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_command_is_a_stop_whatever_the_safety_spec(spec, bad) -> None:
    """The command guard the sites' compiled tick runs (``guard_site``) on a finite, in-limit
    measurement and a non-finite *command*: a stop naming the joint and the value, whatever
    the spec (``safety.enabled: false`` keeps only this check; ``torque_limits: off``'s
    infinite limit once let an inf through, and saturation turned an inf into the limit)."""
    from teleop_rt import config
    from teleop_rt.errors import SafetyStop
    from teleop_rt.hal.signals import Feedback
    from teleop_rt.model import RobotModel
    from teleop_rt.safety import RobotGuard, check_all

    cfg = config.load(PAPER, [])
    model = RobotModel.from_spec(cfg.hsi.robot, "hsi")  # scara_2dof: 20 / 10 N m
    guard = RobotGuard(config.SafetySpec(**spec), model, "hsi", cfg.dt)
    cmd = np.array([1.0, bad])
    stop = rf"^tick 3: hsi joint 1 \(elbow\): commanded torque is {bad}$"
    with pytest.raises(SafetyStop, match=stop):
        check_all(guard, 3, Feedback(2), np.zeros(2), cmd, np.zeros(2))
