"""The compiled tick: the session's packed kernels compute exactly what its blocks compute when
run one by one (the wiring of teleop_rt.lockstep and teleop_rt.site_tick: block order, offsets,
arguments), and packing keeps every block's state and makes its views alias the packed
buffers."""

from __future__ import annotations

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.com.wave import WaveChannel
from teleop_rt.control import Pid
from teleop_rt.flat import Block, Packed
from teleop_rt.safety import check_all
from teleop_rt.session import Session
from tests.conftest import CONFIGS


def test_packing_keeps_state_and_views_alias_the_packed_buffers() -> None:
    ch = WaveChannel([2.0, 0.5], 3, 1e-3, filter_hz=30.0)
    pid = Pid(config.ControllerSpec(kind="pid", kp=2.0, ki=1.0), 2, 1e-3, "c")
    ch.step([0.1, -0.2], [0.3, 0.4])
    port = ch.port_h
    before = (port.f.copy(), port.i.copy(), pid.f.copy(), pid.i.copy())
    packed = Packed([port, pid])
    np.testing.assert_array_equal(port.f, before[0])
    np.testing.assert_array_equal(port.i, before[1])
    np.testing.assert_array_equal(pid.f, before[2])
    assert np.shares_memory(port.effort, packed.f) and np.shares_memory(pid.out, packed.f)
    assert packed.f[packed.index_of(pid, "kp") + 1] == 2.0
    assert packed.f[packed.index_of(port, "alpha")] == port.alpha
    packed.f[packed.index_of(port, "b") + 1] = 7.0
    assert port.b[1] == 7.0


def test_packed_kernels_equal_the_blocks_run_one_by_one() -> None:
    """Exact equality, tick by tick, on the paper experiment with 20 ms of delay (contact, wave
    delay lines, filter, friction compensation, safety checks): a second session's blocks are
    stepped through their own entry points on the first session's feedback."""
    overrides = ["duration_s=1.5", "channel.delay_ms=20"]
    cfg = config.load(CONFIGS / "paper_experiment.yaml", overrides)
    session, shadow = Session(cfg), Session(cfg)
    fb_h, fb_t = session.hsi.feedback, session.to.feedback
    b = config.per_joint(cfg.channel.wave_impedance, 2, "b")
    ch = WaveChannel(b, cfg.delay_ticks, cfg.dt, cfg.channel.wave_filter_hz)
    for k in range(cfg.n_ticks):
        session.step()  # fb_h, fb_t now hold what this tick read
        tau_h, tau_e = fb_h.tau_ext.copy(), -fb_t.tau_ext
        ch.step(fb_h.v, tau_e)
        a_h = shadow.hsi.controller.step(tau_h - ch.tau_c)
        a_t = shadow.to.controller.step(ch.omega_t - fb_t.v)
        g_h = shadow.hsi.computed_torque.step(fb_h.q, fb_h.v, a_h, tau_h)
        g_t = shadow.to.computed_torque.step(fb_t.q, fb_t.v, a_t, fb_t.tau_ext)
        a_des_h, a_des_t = shadow.hsi.computed_torque.a_des, shadow.to.computed_torque.a_des
        check_all(shadow.hsi.guard, k, fb_h, tau_h, g_h, a_des_h)
        check_all(shadow.to.guard, k, fb_t, fb_t.tau_ext, g_t, a_des_t)
        shadow.metrics.add(fb_h.q, fb_t.q, tau_h, tau_e)
        assert session.hsi.tau_cmd.tolist() == g_h.tolist(), k
        assert session.to.tau_cmd.tolist() == g_t.tolist(), k
    assert session.channel.total_energy == ch.total_energy
    assert session.metrics.t_p.tolist() == shadow.metrics.t_p.tolist()
    assert session.metrics.t_tau.tolist() == shadow.metrics.t_tau.tolist()
    assert abs(session.channel.total_energy) > 0.0 and session.metrics.t_tau.sum() > 0.0


def test_a_block_field_may_not_shadow_the_blocks_own_buffers() -> None:
    with pytest.raises(TypeError, match=r"\['f'\]"):
        type("Bad", (Block,), {"SCALARS": ("k", "f")})
