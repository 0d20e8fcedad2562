"""The COM two-port's compiled tick, for both channels: the port variables and waves as one
flat block, the delay lines (whole ticks, zeros until filled, like Drake's DiscreteTimeDelay),
the two exchanges (wave: eq 9-10, see ``teleop_rt.com.wave``; direct: see
``teleop_rt.com.direct``) and the passivity monitor: the power entering the two-port (eq 8),
``omega_c tau_c - omega_t tau_t`` per joint, integrated every tick (eq 7)."""

from __future__ import annotations

import numpy as np

from teleop_rt.flat import Block, as_floats, jit, vec

# float vectors (indices into ChannelBlock.VECTORS)
OMEGA_C, TAU_C, OMEGA_T, TAU_T, U_L, V_L, U_R, V_R, POWER, ENERGY, B, SQRT_2B, SQRT_2_OVER_B = (
    range(13)
)
# scalars, after the vectors
TOTAL_ENERGY, MIN_TOTAL_ENERGY, ALPHA, DT = range(4)
# ints
MODE, DELAY, SLOT, FILTERED = range(4)
DIRECT, WAVE = 0, 1


class ChannelBlock(Block):
    """The COM two-port's signals for n joints and a one-way delay of D ticks (the two delay
    lines, forward then backward, D x n each, are the block's tail)."""

    VECTORS = (
        "omega_c", "tau_c", "omega_t", "tau_t",  # port variables
        "u_l",  # wave sent from the HSI side
        "v_l",  # received at the HSI side (after the optional filter)
        "u_r",  # received at the TO side (after the optional filter)
        "v_r",  # sent from the TO side
        "power",  # omega_c tau_c - omega_t tau_t per joint, W
        "energy",  # its integral per joint, J
        "b", "sqrt_2b", "sqrt_2_over_b",  # wave impedance per joint and its roots
    )  # fmt: skip
    SCALARS = ("total_energy", "min_total_energy", "alpha", "dt")
    INTS = ("mode", "delay_ticks", "slot", "filtered")

    def __init__(self, n: int, delay_ticks: int, dt: float, mode: int) -> None:
        if delay_ticks < 0:
            raise ValueError("delay_ticks must be >= 0")
        super().__init__(n, tail=2 * delay_ticks * n)
        self.mode, self.delay_ticks, self.dt = mode, delay_ticks, dt
        self.alpha = 1.0

    def stored_energy(self) -> float:
        """Energy held in the lines: dt/2 * sum(u^2 + v^2) for waves; 0 for a direct channel,
        which has no such notion (it is not passive)."""
        if self.mode == DIRECT:
            return 0.0
        lines = self.f[self.tail_start :]
        return 0.5 * self.dt * float(lines @ lines)

    def step(self, omega_c: list[float] | np.ndarray, tau_t: list[float] | np.ndarray) -> None:
        """One tick: take the HSI velocity and the TO torque, produce tau_c and omega_t."""
        channel_step(self.f, self.i, self.n, as_floats(omega_c), as_floats(tau_t))


N_VECTORS, N_SCALARS = len(ChannelBlock.VECTORS), len(ChannelBlock.SCALARS)


@jit
def take_inputs(f: np.ndarray, n: int, omega_c: np.ndarray, tau_t: np.ndarray) -> None:
    """Copy this tick's port inputs into the block."""
    wc, tt = vec(f, OMEGA_C, n), vec(f, TAU_T, n)
    for j in range(n):
        wc[j] = omega_c[j]
        tt[j] = tau_t[j]


@jit
def couple_directly(f: np.ndarray, n: int) -> None:
    """Zero delay: omega_t = omega_c, tau_c = tau_t (no algebraic loop)."""
    wc, tt, wt, tc = vec(f, OMEGA_C, n), vec(f, TAU_T, n), vec(f, OMEGA_T, n), vec(f, TAU_C, n)
    for j in range(n):
        wt[j] = wc[j]
        tc[j] = tt[j]


@jit
def line_slots(f: np.ndarray, i: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """This tick's slot of the forward and backward lines: it holds the sample pushed D ticks
    ago (zeros before), to be read, then overwritten with this tick's sample."""
    d, slot = i[DELAY], i[SLOT]
    start = N_VECTORS * n + N_SCALARS + slot * n
    return f[start : start + n], f[start + d * n : start + d * n + n]


@jit
def advance_lines(i: np.ndarray) -> None:
    slot = i[SLOT] + 1
    i[SLOT] = 0 if slot == i[DELAY] else slot


@jit
def account_power(f: np.ndarray, n: int) -> None:
    """Update power, energy (per joint), total_energy and its running minimum (NaN counts as a
    new minimum, so a diverged channel never looks passive)."""
    wc, tc, wt, tt = vec(f, OMEGA_C, n), vec(f, TAU_C, n), vec(f, OMEGA_T, n), vec(f, TAU_T, n)
    power, energy = vec(f, POWER, n), vec(f, ENERGY, n)
    s = N_VECTORS * n
    dt = f[s + DT]
    total = 0.0
    for j in range(n):
        p = wc[j] * tc[j] - wt[j] * tt[j]
        power[j] = p
        energy[j] += p * dt
        total += energy[j]
    f[s + TOTAL_ENERGY] = total
    if not total >= f[s + MIN_TOTAL_ENERGY]:
        f[s + MIN_TOTAL_ENERGY] = total


@jit
def channel_step(
    f: np.ndarray, i: np.ndarray, n: int, omega_c: np.ndarray, tau_t: np.ndarray
) -> None:
    """One tick of either channel (the mode is in the block)."""
    take_inputs(f, n, omega_c, tau_t)
    if i[DELAY] == 0:
        couple_directly(f, n)
    elif i[MODE] == WAVE:
        wave_exchange(f, i, n)
    else:
        direct_exchange(f, i, n)
    account_power(f, n)


@jit
def direct_exchange(f: np.ndarray, i: np.ndarray, n: int) -> None:
    """Velocity forward, torque back, each delayed by D ticks (the direct channel)."""
    forward, backward = line_slots(f, i, n)
    wc, tt, wt, tc = vec(f, OMEGA_C, n), vec(f, TAU_T, n), vec(f, OMEGA_T, n), vec(f, TAU_C, n)
    for j in range(n):
        wt[j] = forward[j]
        tc[j] = backward[j]
        forward[j] = wc[j]
        backward[j] = tt[j]
    advance_lines(i)


@jit
def wave_exchange(f: np.ndarray, i: np.ndarray, n: int) -> None:
    """Eq 9-10 with D >= 1 ticks (see teleop_rt.com.wave for the derivation)."""
    forward, backward = line_slots(f, i, n)  # u_l[k-D] and v_r[k-D], then this tick's
    s = N_VECTORS * n
    alpha, filtered = f[s + ALPHA], i[FILTERED] != 0
    b, s2b, s2ob = vec(f, B, n), vec(f, SQRT_2B, n), vec(f, SQRT_2_OVER_B, n)
    wc, tt, wt, tc = vec(f, OMEGA_C, n), vec(f, TAU_T, n), vec(f, OMEGA_T, n), vec(f, TAU_C, n)
    u_l, v_l, u_r, v_r = vec(f, U_L, n), vec(f, V_L, n), vec(f, U_R, n), vec(f, V_R, n)
    for j in range(n):
        # received waves, through the optional first-order low-pass
        if filtered:
            u_r[j] += alpha * (forward[j] - u_r[j])
            v_l[j] += alpha * (backward[j] - v_l[j])
        else:
            u_r[j] = forward[j]
            v_l[j] = backward[j]
        w = wc[j]
        tau = tt[j]
        # HSI side: tau_c = b omega_c - sqrt(2b) v_l ; u_l = sqrt(2b) omega_c - v_l
        tc[j] = b[j] * w - s2b[j] * v_l[j]
        u_l[j] = s2b[j] * w - v_l[j]
        # TO side: omega_t = (sqrt(2b) u_r - tau_t) / b ; v_r = u_r - sqrt(2/b) tau_t
        wt[j] = (s2b[j] * u_r[j] - tau) / b[j]
        v_r[j] = u_r[j] - s2ob[j] * tau
        forward[j] = u_l[j]
        backward[j] = v_r[j]
    advance_lines(i)
