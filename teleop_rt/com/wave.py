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

from teleop_rt.com.delay import DelayLine
from teleop_rt.com.energy import account_power


class WaveChannel:
    """The COM two-port for n joints with a one-way delay of ``delay_ticks`` ticks.

    Signals are lists of floats, one entry per joint (the scalar path is several times faster
    than numpy for a few joints); ``step`` updates them in place.
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
        if delay_ticks < 0:
            raise ValueError("delay_ticks must be >= 0")
        n = len(b)
        self.n, self.b, self.dt, self.delay_ticks = n, b, dt, delay_ticks
        self.sqrt_2b = [math.sqrt(2.0 * x) for x in b]
        self.sqrt_2_over_b = [math.sqrt(2.0 / x) for x in b]
        # the filter acts on received waves; with D = 0 there are none (direct coupling)
        self.filter_hz = filter_hz if delay_ticks > 0 else None
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * filter_hz * dt) if self.filter_hz else 1.0
        self.u_line = DelayLine(delay_ticks, n) if delay_ticks else None
        self.v_line = DelayLine(delay_ticks, n) if delay_ticks else None
        zeros = [0.0] * n
        # Signals of the current tick (read by recording and tests).
        self.omega_c = zeros.copy()
        self.tau_c = zeros.copy()
        self.omega_t = zeros.copy()
        self.tau_t = zeros.copy()
        self.u_l = zeros.copy()  # sent from the HSI side
        self.v_r = zeros.copy()  # sent from the TO side
        self.u_r = zeros.copy()  # received at the TO side (after the optional filter)
        self.v_l = zeros.copy()  # received at the HSI side (after the optional filter)
        self.power = zeros.copy()  # omega_c tau_c - omega_t tau_t per joint, W
        self.energy = zeros.copy()  # its integral per joint, J
        self.total_energy = 0.0
        self.min_total_energy = 0.0

    def step(self, omega_c: list[float], tau_t: list[float]) -> None:
        """One tick: take the HSI velocity and the TO torque, produce tau_c and omega_t."""
        self.omega_c[:] = omega_c
        self.tau_t[:] = tau_t
        if self.u_line is None:
            self.omega_t[:] = omega_c
            self.tau_c[:] = tau_t
        else:
            self._exchange()
        account_power(self)

    def _exchange(self) -> None:
        received_u = self.u_line.pop()
        received_v = self.v_line.pop()
        alpha, filtered = self.alpha, self.filter_hz is not None
        b, s2b, s2ob = self.b, self.sqrt_2b, self.sqrt_2_over_b
        u_r, v_l, u_l, v_r = self.u_r, self.v_l, self.u_l, self.v_r
        for j in range(self.n):
            # received waves, through the optional first-order low-pass
            if filtered:
                u_r[j] += alpha * (received_u[j] - u_r[j])
                v_l[j] += alpha * (received_v[j] - v_l[j])
            else:
                u_r[j] = received_u[j]
                v_l[j] = received_v[j]
            w = self.omega_c[j]
            tau_t = self.tau_t[j]
            # HSI side: tau_c = b omega_c - sqrt(2b) v_l ; u_l = sqrt(2b) omega_c - v_l
            self.tau_c[j] = b[j] * w - s2b[j] * v_l[j]
            u_l[j] = s2b[j] * w - v_l[j]
            # TO side: omega_t = (sqrt(2b) u_r - tau_t) / b ; v_r = u_r - sqrt(2/b) tau_t
            self.omega_t[j] = (s2b[j] * u_r[j] - tau_t) / b[j]
            v_r[j] = u_r[j] - s2ob[j] * tau_t
        self.u_line.push(u_l)
        self.v_line.push(v_r)

    def stored_energy(self) -> float:
        """Wave energy held in the delay lines: dt/2 * sum(u^2 + v^2) over buffered samples."""
        if self.u_line is None:
            return 0.0
        return 0.5 * self.dt * (self.u_line.sum_of_squares() + self.v_line.sum_of_squares())
