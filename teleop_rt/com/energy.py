"""Passivity monitor shared by the channels: the power entering the two-port (eq 8),
``omega_c tau_c - omega_t tau_t`` per joint, integrated every tick (eq 7)."""

from __future__ import annotations

from typing import Any


def account_power(ch: Any) -> None:
    """Update ``power``, ``energy`` (per joint), ``total_energy`` and its running minimum
    (NaN counts as a new minimum, so a diverged channel never looks passive)."""
    dt, energy, power = ch.dt, ch.energy, ch.power
    omega_c, tau_c, omega_t, tau_t = ch.omega_c, ch.tau_c, ch.omega_t, ch.tau_t
    total = 0.0
    for j in range(ch.n):
        p = omega_c[j] * tau_c[j] - omega_t[j] * tau_t[j]
        power[j] = p
        energy[j] += p * dt
        total += energy[j]
    ch.total_energy = total
    if not total >= ch.min_total_energy:
        ch.min_total_energy = total
