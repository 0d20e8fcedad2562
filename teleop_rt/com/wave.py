"""Wave-variable (scattering) channel, eq 9-10 of the paper, per joint.

Ports and power (eq 8): the HSI side puts flow ``omega_c`` in and gets effort ``tau_c`` back;
the TO side puts effort ``tau_t`` in and gets flow ``omega_t`` back; power into the channel is
``omega_c tau_c - omega_t tau_t``. Waves (eq 9), b > 0 the wave impedance per joint:

    u_l = (b omega_c + tau_c) / sqrt(2b)      v_l = (b omega_c - tau_c) / sqrt(2b)
    u_r = (b omega_t + tau_t) / sqrt(2b)      v_r = (b omega_t - tau_t) / sqrt(2b)

Solved for what each side computes from what it knows this tick:

    HSI:  tau_c = b omega_c - sqrt(2b) v_l        u_l = sqrt(2b) omega_c - v_l
    TO:   omega_t = (sqrt(2b) u_r - tau_t) / b    v_r = u_r - sqrt(2/b) tau_t

and eq 10 with D whole ticks: ``u_r[k] = u_l[k-D]``, ``v_l[k] = v_r[k-D]``. Since
``omega tau = (u^2 - v^2) / 2`` the energy that entered the channel by tick k equals
``dt/2`` times the sum of squares of the waves held in the two delay lines: the discrete channel
is exactly passive. D = 0 couples directly (omega_t = omega_c, tau_c = tau_t), no algebraic loop.

Optional: a first-order low-pass on each received wave (``y += alpha (x - y)``). Its output is a
convex combination of past inputs, so sum(y^2) <= sum(x^2) for every prefix: the filtered channel
stays passive (energy in >= energy stored), and the filter damps the ringing that explicit 1 kHz
terminations show against stiff contact.
"""

from __future__ import annotations

from teleop_rt.com.channel import TwoPort, make_ports


class WaveChannel(TwoPort):
    """The COM two-port for n joints with a one-way delay of ``delay_ticks`` ticks: the two
    sites' wave ports (``teleop_rt.com.port``) joined by an in-process link."""

    def __init__(
        self,
        wave_impedance: list[float],
        delay_ticks: int,
        dt: float,
        filter_hz: float | None = None,
    ) -> None:
        b = [float(x) for x in wave_impedance]
        port_h, port_t = make_ports("wave", b, delay_ticks, dt, filter_hz)
        super().__init__(len(b), port_h, port_t, delay_ticks, dt)
        self.filter_hz = port_h.filter_hz
