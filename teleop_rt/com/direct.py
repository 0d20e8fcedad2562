"""Plain delayed force-feedback channel (no wave transform), for comparison with the wave
channel: ``omega_t[k] = omega_c[k - D]`` and ``tau_c[k] = tau_t[k - D]``.

It is not passive: the energy that enters (``omega_c tau_c - omega_t tau_t``, integrated) can go
negative, and against a stiff wall the loop goes unstable from a modest delay on. The same
signal names as ``WaveChannel`` (waves stay zero) let sessions and logs use either.
"""

from __future__ import annotations

from teleop_rt.com.channel import TwoPort, make_ports


class DirectChannel(TwoPort):
    """Velocity forward, torque back, each delayed by ``delay_ticks`` whole ticks."""

    def __init__(self, n: int, delay_ticks: int, dt: float) -> None:
        port_h, port_t = make_ports("direct", [1.0] * n, delay_ticks, dt, None)
        super().__init__(n, port_h, port_t, delay_ticks, dt)
