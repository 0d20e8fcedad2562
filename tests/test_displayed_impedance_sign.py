"""The sign convention, decided by the paper's eq 20-24: the running blocks (computed torque on
the simulated SCARAs, P controllers C1 and C2, the wave channel) in the paper's open chain
(operator velocity omega_o imposed on the channel, damper operator Z_o on the HSI, tau_h
measured) display Z_h = tau_h / omega_o = G_tau Z_c(G_omega Z_e)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop_rt.analysis.impedance import ImpedanceParams, displayed_impedance
from teleop_rt.com.wave import WaveChannel
from teleop_rt.config import ControllerSpec, DamperOperatorSpec, RobotSpec
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.hal.sim import SimBackend
from teleop_rt.model import RobotModel
from teleop_rt.world import JointDamperOperator, JointSpringDamper
from tests.conftest import SCARA_URDF, lock_in

DT = 1e-3
M1, M2, C1, C2, Z_O, B = 0.1, 0.1, 2.0, 20.0, 10.0, 2.0
Q0 = [-0.8, 1.8]
JOINT = 1  # the excited joint; the other must stay still (decoupling)


def measure_open_chain(omega, delay_ms, k_env, filter_hz=None, flip_c1=False, seconds=2.0):
    spec = RobotSpec(urdf=SCARA_URDF, ee_frame="tool")
    hsi_plant = SimBackend(
        RobotModel.from_spec(spec, "hsi"),
        [JointDamperOperator(DamperOperatorSpec(kind="damper", damping_nm_s_per_rad=Z_O), 2)],
        np.array(Q0),
        DT,
    )
    to_plant = SimBackend(
        RobotModel.from_spec(spec, "to"),
        [JointSpringDamper([k_env] * 2, [0.0] * 2, Q0)],
        np.array(Q0),
        DT,
    )
    ct_h = ComputedTorque(RobotModel.from_spec(spec, "h"), [M1, M1], True)
    ct_t = ComputedTorque(RobotModel.from_spec(spec, "t"), [M2, M2], True)
    c1 = Pid(ControllerSpec(kind="p", kp=C1), 2, DT, "c1")
    c2 = Pid(ControllerSpec(kind="p", kp=C2), 2, DT, "c2")
    channel = WaveChannel([B, B], round(delay_ms), DT, filter_hz)
    settle = round(seconds / DT)
    ticks = 2 * settle
    w_o, tau_h, q_other = np.zeros(ticks), np.zeros(ticks), np.zeros(ticks)
    sign = -1.0 if flip_c1 else 1.0
    for k in range(ticks):
        fb_h, fb_t = hsi_plant.read(), to_plant.read()
        w = 0.05 * math.sin(omega * k * DT)
        omega_c = [0.0, 0.0]
        omega_c[JOINT] = w
        tau_e = [-x for x in list(fb_t.tau_ext)]
        channel.step(omega_c, tau_e)
        th = list(fb_h.tau_ext)
        a_h = c1.step([sign * (th[j] - channel.tau_c[j]) for j in range(2)])
        a_t = c2.step([channel.omega_t[j] - fb_t.v[j] for j in range(2)])
        hsi_plant.write(ct_h.step(fb_h.q, fb_h.v, a_h, th, fb_h.v_list))
        to_plant.write(ct_t.step(fb_t.q, fb_t.v, a_t, list(fb_t.tau_ext), fb_t.v_list))
        w_o[k], tau_h[k], q_other[k] = w, th[JOINT], fb_h.q[1 - JOINT] - Q0[1 - JOINT]
    z = lock_in(tau_h[settle:], omega, DT) / lock_in(w_o[settle:], omega, DT)
    return z, np.abs(q_other).max()


CASES = [
    # (delay_ms, k_env N m/rad, filter_hz): cases whose open chain settles within 2 s (a soft
    # spring behind 50 ms rings for longer; issue #4's bode reports such cases as unsettled)
    (0, 20.0, None),
    (20, 0.0, None),
    (20, 20.0, 30.0),
    (50, 0.0, 30.0),
]


@pytest.mark.parametrize("delay_ms,k_env,filter_hz", CASES)
@pytest.mark.parametrize("hz", [0.5, 1.0])
def test_running_blocks_display_eq_20_to_24(delay_ms, k_env, filter_hz, hz) -> None:
    omega = 2 * math.pi * hz
    z, other = measure_open_chain(omega, delay_ms, k_env, filter_hz)
    params = ImpedanceParams(
        m1=M1,
        m2=M2,
        c1=C1,
        c2=C2,
        z_o=Z_O,
        b=B,
        delay_s=delay_ms / 1000,
        env_stiffness=k_env,
        wave_filter_hz=filter_hz,
    )
    analytic = complex(displayed_impedance(1j * omega, params))
    # continuous-time analytic vs the 1 kHz loop: the one-tick sensing and hold cost
    # O(omega dt) ~ 0.6 % here; 2 % in magnitude and 2 degrees in phase (issue #4's bar)
    assert abs(abs(z) / abs(analytic) - 1) < 0.02
    assert abs(math.degrees(np.angle(z / analytic))) < 2.0
    assert other < 1e-9  # the other joint never moves: computed torque decouples


def test_free_space_without_delay_displays_nothing() -> None:
    z, _ = measure_open_chain(2 * math.pi * 0.5, 0, 0.0)
    assert abs(z) < 1e-9  # eq 27 with Z_e = 0: Z_h = 0


def test_the_opposite_sign_of_c1_does_not_display_eq_20() -> None:
    # C1 acting on tau_c - tau_h with this stack's tau_h (operator on HSI) is positive feedback
    omega = 2 * math.pi * 0.5
    z, _ = measure_open_chain(omega, 0, 20.0, flip_c1=True)
    params = ImpedanceParams(
        m1=M1, m2=M2, c1=C1, c2=C2, z_o=Z_O, b=B, delay_s=0.0, env_stiffness=20.0
    )
    analytic = complex(displayed_impedance(1j * omega, params))
    assert not np.isfinite(z) or abs(z / analytic - 1) > 0.5
