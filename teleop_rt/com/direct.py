"""Plain delayed force-feedback channel (no wave transform), for comparison with the wave
channel: ``omega_t[k] = omega_c[k - D]`` and ``tau_c[k] = tau_t[k - D]``.

It is not passive: the energy that enters (``omega_c tau_c - omega_t tau_t``, integrated) can go
negative, and against a stiff wall the loop goes unstable from a modest delay on. The same
signal names as ``WaveChannel`` (waves stay zero) let sessions and logs use either.
"""

from __future__ import annotations

from teleop_rt.com.delay import DelayLine
from teleop_rt.com.energy import account_power


class DirectChannel:
    """Velocity forward, torque back, each delayed by ``delay_ticks`` whole ticks."""

    def __init__(self, n: int, delay_ticks: int, dt: float) -> None:
        if delay_ticks < 0:
            raise ValueError("delay_ticks must be >= 0")
        self.n, self.dt, self.delay_ticks = n, dt, delay_ticks
        self.forward = DelayLine(delay_ticks, n) if delay_ticks else None
        self.backward = DelayLine(delay_ticks, n) if delay_ticks else None
        zeros = [0.0] * n
        self.omega_c, self.tau_c = zeros.copy(), zeros.copy()
        self.omega_t, self.tau_t = zeros.copy(), zeros.copy()
        self.u_l, self.v_l, self.u_r, self.v_r = (zeros.copy() for _ in range(4))
        self.power, self.energy = zeros.copy(), zeros.copy()
        self.total_energy = 0.0
        self.min_total_energy = 0.0

    def step(self, omega_c: list[float], tau_t: list[float]) -> None:
        """One tick: the HSI velocity goes out, the TO torque comes back, both delayed."""
        self.omega_c[:] = omega_c
        self.tau_t[:] = tau_t
        if self.forward is None:
            self.omega_t[:] = omega_c
            self.tau_c[:] = tau_t
        else:
            self.omega_t[:] = self.forward.pop()
            self.tau_c[:] = self.backward.pop()
            self.forward.push(omega_c)
            self.backward.push(tau_t)
        account_power(self)

    def stored_energy(self) -> float:
        """No stored-energy notion for a non-passive channel (kept for the common interface)."""
        return 0.0
