"""P / PID controllers (eq 4, 14): the discrete law against its definition, anti-windup."""

from __future__ import annotations

import pytest

from teleop_rt.config import ControllerSpec
from teleop_rt.control import Pid

DT = 1e-3


def test_p_controller_is_a_gain_per_joint() -> None:
    pid = Pid(ControllerSpec(kind="p", kp=[2.0, 20.0]), 2, DT, "c")
    assert pid.step([0.5, -0.1]) == pytest.approx([1.0, -2.0])


def test_integral_accumulates_ki_e_dt() -> None:
    pid = Pid(ControllerSpec(kind="pid", kp=0.0, ki=4.0), 1, DT, "c")
    outs = [pid.step([0.5])[0] for _ in range(1000)]
    # forward Euler: the output at tick k holds the integral of the k previous ticks
    assert outs[0] == 0.0
    assert outs[-1] == pytest.approx(4.0 * 0.5 * 999 * DT, rel=1e-12)


def test_derivative_of_a_ramp_is_its_slope_after_the_filter_settles() -> None:
    tf = 0.01
    pid = Pid(ControllerSpec(kind="pid", kp=0.0, kd=2.0, derivative_filter_s=tf), 1, DT, "c")
    for k in range(500):  # 50 filter time constants
        out = pid.step([3.0 * k * DT])[0]
    assert out == pytest.approx(2.0 * 3.0, rel=1e-9)


def test_integral_limit_clamps_the_integral_term() -> None:
    spec = ControllerSpec(kind="pid", kp=0.0, ki=10.0, integral_limit=0.2)
    pid = Pid(spec, 1, DT, "c")
    for _ in range(5000):
        out = pid.step([1.0])[0]
    assert out == pytest.approx(0.2)
    assert pid.integral[0] == pytest.approx(0.2)


def test_output_limit_stops_integration_while_saturated() -> None:
    """Conditional integration: while the output sits at the limit in the direction of the
    error the integrator holds, so it recovers at once when the error reverses."""
    spec = ControllerSpec(kind="pid", kp=1.0, ki=5.0, output_limit=1.0)
    pid = Pid(spec, 1, DT, "c")
    for _ in range(3000):
        out = pid.step([2.0])[0]  # kp e alone already exceeds the limit
    assert out == 1.0 and pid.saturated[0]
    assert abs(pid.integral[0]) < 1e-12  # no windup at all
    # without anti-windup the same run would carry an integral of 5 * 2 * 3 s = 30
    out = pid.step([-0.5])[0]
    assert out == pytest.approx(-0.5)


def test_pid_reset_forgets_its_state() -> None:
    pid = Pid(ControllerSpec(kind="pid", kp=1.0, ki=1.0, kd=1.0), 1, DT, "c")
    for k in range(10):
        pid.step([float(k)])
    pid.reset()
    assert pid.integral == [0.0] and pid.deriv == [0.0]
