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

import math

from teleop_rt.com.channel import WAVE, ChannelBlock


class WaveChannel(ChannelBlock):
    """The COM two-port for n joints with a one-way delay of ``delay_ticks`` ticks.

    Signals are numpy views of one flat block (see ``teleop_rt.flat``); ``step`` runs the
    compiled exchange of ``teleop_rt.com.channel`` and updates them in place.
    """

    def __init__(
        self,
        wave_impedance: list[float],
        delay_ticks: int,
        dt: float,
        filter_hz: float | None = None,
    ) -> None:
        b = [float(x) for x in wave_impedance]
        if any(not x > 0 for x in b):
            raise ValueError("wave impedance b must be > 0 on every joint")
        super().__init__(len(b), delay_ticks, dt, WAVE)
        self.b[:] = b
        self.sqrt_2b[:] = [math.sqrt(2.0 * x) for x in b]
        self.sqrt_2_over_b[:] = [math.sqrt(2.0 / x) for x in b]
        # the filter acts on received waves; with D = 0 there are none (direct coupling)
        self.filter_hz = filter_hz if delay_ticks > 0 else None
        self.filtered = int(self.filter_hz is not None)
        if self.filter_hz:
            self.alpha = 1.0 - math.exp(-2.0 * math.pi * self.filter_hz * dt)
