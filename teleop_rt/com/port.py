"""One site's port of the COM two-port, and the packets the two ports exchange.

The paper's channel (eq 8-10) has a port at each site. The HSI's port takes the flow
``omega_c = v_h`` and gives the effort ``tau_c``; the TO's takes the effort ``tau_t = tau_e``
and gives the flow ``omega_t``. Each port knows only its own variables and what reaches it in
packets from the other (``Packet``: the sender's tick, sequence number, its port input ``x``,
its outgoing wave and the energy that has crossed its port). The wave transform of eq 9, solved
for what each side knows in its tick (derivation in ``teleop_rt.com.wave``):

    HSI:  tau_c = b omega_c - sqrt(2b) v_l          u_l = sqrt(2b) omega_c - v_l
    TO:   omega_t = (sqrt(2b) u_r - tau_t) / b      v_r = u_r - sqrt(2/b) tau_t

where the received wave (v_l at the HSI, u_r at the TO) is the peer's sent wave through the
optional first-order low-pass. With no delay the ports couple directly (tau_c = tau_t,
omega_t = omega_c, from the peer's port input of the same tick); the direct channel mode is
plain delayed force feedback (the peer's port input, delayed). What the link did not deliver is
a zero packet (a zero wave is passive; holding the last one is not).

Each port also integrates the power into the channel at its side (eq 8): ``omega_c tau_c`` at
the HSI, ``-omega_t tau_t`` at the TO; their sum is the channel's energy (eq 7).

Beyond the paper (issue 17): what a site does with a packet that did not arrive, and how it
stays passive when the network varies its delay, loses, duplicates or reorders packets:

- ``wave`` with ``reconstruction``:
  ``zero``     a missing packet is a zero wave (passive; each loss shifts the TO for good);
  ``hold``     the last wave is held through a loss: the plain channel, NOT passive (a held wave
               is energy the peer never sent) -- kept to show what goes wrong unprotected;
  ``integral`` Niemeyer & Slotine's wave integral without its bound: packets carry the sender's
               integral of its wave (which also carries position), and a site that missed up
               to ``CATCH_UP`` samples catches the integral up in one tick; NOT passive (a jump
               forward after a delay step down replays the skipped samples in one tick, faster
               than they were sent);
  ``bounded``  the wave integral with the energy bound (Niemeyer & Slotine, IJRR 2004): packets
               also carry the sender's cumulative wave energy (monotone: robust to loss and
               reordering), and the wave a site emits is clipped so that the wave energy it has
               emitted never exceeds what the peer has sent, per joint. With consecutive packets
               and the integral in step it uses the received wave as it is, so with no loss it
               computes exactly what ``zero`` computes, bit for bit (the bound compares the same
               sums in the same order, and never acts). The budget is honest (issue 23): only
               the energy of waves that reached the port in time (``got_energy``): each sample
               used, and in a catch-up the samples it catches up, which only that tick may
               spend; after a gap longer than ``CATCH_UP`` the skipped samples bring nothing
               (crediting the peer's cumulative energy let a stale held wave spend it in the
               next outage: a ratchet into a joint limit). A held wave expires after
               ``HOLD_TICKS`` ticks of silence, and what it had left of the budget with it.
  ``corrected`` ``bounded`` with position-drift compensation: the wave integral's debt (the
               peer's integral minus the one used: what an outage lost or the bound cut) is
               kept and paid back at ``1 / wave_drift_time_s`` on the waves used, within the
               same honest budget (wave integrals with position correction, Niemeyer &
               Slotine, IJRR 2004; position tracking with wave variables, Chopra, Spong,
               Hirche & Buss, ACC 2003). With no loss the debt is exactly 0: ``bounded`` bit
               for bit. The time constant (default ``WAVE_DRIFT_TIME_S``) is the drift
               correction's gain: the pay-back replays what the port missed (after a delay
               step down, the samples the playout skipped) and, in free space, the TO's
               catch-up comes back to the HSI as a wave the operator feels; a longer one
               trades T_p for T_tau (docs/transparency_under_loss.md, "s36"). How the debt
               arose sets its rate (s37): the share of a packet's new debt that a change of
               the delay brought under the ``newest`` playout (packets skipped with no silence
               at a drop, or silent ticks with none missed as it grows: |missed - silent| of
               max(missed, silent)) is a skip debt, paid at ``1 / wave_skip_time_s`` (an
               option, off by default: one debt; 2 s meets the foam sawtooth row, as nothing
               of the HSI's motion was lost, only replayed late, but under jitter at newest
               D = 1 ms it costs T_p and drift); an outage's or a loss's (as many silent ticks
               as packets missed: motion lost) keeps the fast rate. The fixed playout uses
               packet k - D at tick k, so the two never differ there: no skip debt.
  ``reflected`` ``corrected`` with energy reflection: the two-port needs only the sum over
               both directions, sum(u_l^2 - u_r^2) + sum(v_r^2 - v_l^2) >= 0, not each
               direction's. In a static push a port takes almost no net power (the wave it uses
               goes back in the wave it sends), so through a loss the TO brakes (omega_t = 0,
               all of the wave reflected) and the HSI holds the TO's last effort; a port may
               take out of the channel, per tick, (y^2 - sent^2) dt / 2, what its budget and
               the energy it sent allow, and the energy it used beyond its budget is taken off
               the wave energy it DECLARES in its packets (monotone; the peer's budget is what
               was declared), so the peer cannot spend the reflected energy again (the energy
               observers of TDPA moved onto the waves: Ryu, Artigas & Preusche, Mechatronics
               2010; the idea of crediting the energy a port reflects, after the energy
               reflection in TDPA of Panzirsch, Ryu & Ferre, Mechatronics 2019, as issue 23
               cites it: the derivation here is our own and was not checked against it).
               Proof: OUT_i <= G_i + S_i - D_i, G_i <= D_j (now), so OUT_h + OUT_t <= S_h + S_t.
               With no loss D = S and the bound never acts: ``bounded`` bit for bit.
- ``tdpa``: the time-domain passivity approach (Ryu, Artigas & Preusche, Mechatronics 2010):
  velocity forward, torque back (the paper's force-feedback coupling), the last value held
  through a gap of up to ``HOLD_TICKS``, zero after; at each port a passivity observer of the
  energy that entered (E_in) and left (E_out) it, per joint (monotone), each site sending its
  E_in. A site whose E_out would exceed the peer's E_in it has received dissipates the
  difference in that tick: an impedance-type passivity controller at the HSI (tau_c += beta
  omega_c: its output is a torque), an admittance-type one at the TO (omega_t -= alpha tau_t:
  its output is a velocity). With no delay the coupling is direct and lossless and no
  controller runs. Position drift (the TO's integral of its output against the HSI's integral
  of its velocity, which packets carry): the TO adds ``drift_rate`` times the difference to its
  velocity, before the passivity controller, which keeps the sum passive (after Artigas et al.,
  "Position drift compensation in time domain passivity based teleoperation", IROS 2010).
"""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.declarations import (
    BOUNDED,
    CORRECTED,
    DEFAULT_MODE,
    DEFAULT_RECONSTRUCTION,
    DIRECT,
    HOLD,
    MODES,
    RECONSTRUCTIONS,
    REFLECTED,
    TDPA,
    WAVE,
    WAVE_B_FLOOR,
    WAVE_B_HOLD_S,
    WAVE_B_RATE,
    WAVE_DRIFT_TIME_S,
    WAVE_SKIP_TIME_S,
    ZERO,
    require_delay_ticks,
)
from teleop_rt.flat import Block, Int, Scalar, Vector, jit, vec

HSI, TO = 0, 1  # a port's side
CATCH_UP = 10  # the most missed packets the wave integral catches up in one tick
HOLD_TICKS = 10  # TDPA holds the peer's last value this long through a gap, then zero


class Packet(Block):
    """What one site sends the other per tick (the link's unit); zeros mean none arrived."""

    x = Vector("the sender's port input: omega_c from the HSI, tau_t from the TO")
    wave = Vector("the sender's outgoing wave: u_l from the HSI, v_r from the TO")
    wave_sum = Vector("dt times the sum of the waves sent (the wave integral)")
    x_sum = Vector("dt times the sum of the sender's port inputs (the HSI's: its position)")
    wave_energy = Vector("dt / 2 times the sum of the squared waves sent, J (monotone)")
    e_in = Vector("energy that entered the sender's port, J (monotone; TDPA)")
    e_out = Vector("energy that left it, J (monotone)")
    energy = Scalar("energy that has crossed the sender's port, J (cumulative)")
    tick = Int("the sender's tick")
    seq = Int("sequence number")
    valid = Int("1: a packet; 0: none arrived")
    unsent = Int("1: the sender's codec sent nothing this tick (the links carry nothing)")
    engaged = Int("the sender's operator map: 1 coupled, 0 decoupled (the HSI's clutch pressed "
                  "or its operator away; teleop_rt.mapping); the wire carries 0 or 1")


class Port(Block):
    """One side's port: its wave transform and the energy that crossed it."""

    b = Vector("wave impedance per joint, N m s/rad", param=True)
    sqrt_2b = Vector(param=True)
    sqrt_2_over_b = Vector(param=True)
    b_now = Vector("the wave impedance in use, N m s/rad: ``b`` unless scheduled by the delay "
                   "(``schedule_b``)")
    sqrt_2b_now = Vector()
    sqrt_2_over_b_now = Vector()
    pos_ref = Vector("the TO's position offset from the HSI's when b left b_0 (the correction "
                     "removes only what the schedule added to it)")
    flow = Vector("omega: the HSI's input (omega_c), the TO's output (omega_t), rad/s")
    effort = Vector("tau: the HSI's output (tau_c), the TO's input (tau_t), N m")
    wave_out = Vector("the wave this port sends: u_l (HSI), v_r (TO)")
    wave_in = Vector("the wave received, after the optional filter: v_l (HSI), u_r (TO)")
    power = Vector("power into the channel at this port, W")
    energy = Vector("its integral per joint, J")
    e_in = Vector("energy that entered the channel here, J (monotone; TDPA's observer)")
    e_out = Vector("energy that left the channel here, J (monotone)")
    wave_sum = Vector("dt times the sum of the waves sent (the wave integral)")
    wave_energy = Vector("dt / 2 times the sum of the squared waves sent, J")
    held = Vector("the last received value (wave, or TDPA's peer input), held through a loss")
    peer_sum = Vector("the peer's wave integral, as of its newest packet")
    peer_energy = Vector("the peer's wave energy sent, J, as of its newest packet")
    used_sum = Vector("dt times the sum of the waves used here (before the filter)")
    used_energy = Vector("dt / 2 times the sum of their squares, J")
    peer_e_in = Vector("the peer's E_in, J, as of its newest packet (TDPA)")
    x_sum = Vector("dt times the sum of this port's inputs")
    peer_x_sum = Vector("the peer's, as of its newest packet")
    out_sum = Vector("dt times the sum of this port's outputs (TDPA's TO: its position)")
    limited = Vector("energy the protection removed: the bound's, or TDPA's dissipation, J")
    got_energy = Vector("dt / 2 times the sum of the squared waves that reached this port in "
                        "time, J (the bound's honest budget)")
    debt = Vector("``corrected``: the peer's wave integral minus the one used, after a packet")
    skip_debt = Vector("the part of ``debt`` a delay change brought under ``newest`` (packets "
                       "skipped with no silence, or silent ticks with none missed)")
    out_energy = Vector("dt / 2 times the sum of the squared waves the filter gave the port, J")
    banked = Vector("the bound's budget left after the last packet, J")
    declared = Vector("``reflected``: the wave energy declared to the peer, J: that sent less "
                      "what this port emitted beyond its budget (monotone)")
    total_energy = Scalar("sum over joints, J")
    balance = Scalar("energy received minus emitted, as the method accounts it, J (joints: min)")
    min_balance = Scalar("its running minimum, J")
    alpha = Scalar("received-wave low-pass coefficient", param=True)
    drift_rate = Scalar("TDPA's position-drift compensation at the TO, 1/s (0: off)", param=True)
    wave_drift_rate = Scalar("``corrected``: 1 / wave_drift_time_s, 1/s", param=True)
    skip_rate = Scalar("``corrected``: 1 / wave_skip_time_s, the skip debt's rate, 1/s (0: "
                       "off, one debt at wave_drift_rate)", param=True)
    b_floor = Scalar("the scheduled b's floor, a share of ``b``", param=True)
    b_rate = Scalar("the scheduled b moves by at most this share of ``b`` per second, 1/s",
                    param=True)  # fmt: skip
    dt = Scalar(param=True)
    side = Int("HSI or TO", param=True)
    b_schedule = Int("1: b scheduled by the age of the packets used (``schedule_b``)", param=True)
    now_tick = Int("this site's tick (set by the port stage: a packet's age is this minus its "
                   "sender tick)")
    age_floor = Int("the least age of a packet used so far, ticks (the path's own delay: the "
                    "schedule's reference; -1 none yet)")
    b_moved = Int("ticks left of the TO's position correction after b last differed from b_0")
    b_hold_ticks = Int("the correction stays on this long after b is back at b_0", param=True)
    mode = Int("DIRECT, WAVE or TDPA", param=True)
    delay_ticks = Int("nominal one-way delay; 0 couples directly", param=True)
    filtered = Int("1: received waves are low-passed", param=True)
    reconstruction = Int("a wave channel's: ZERO, HOLD, INTEGRAL, BOUNDED, ... (above)", param=True)
    last_seq = Int("sequence number of the newest packet used (-1: none)")
    missing = Int("ticks since the last packet arrived")
    acted = Int("ticks in which the protection acted (bound or passivity controller)")
    # the deadband codec's (teleop_rt.com.codec; all idle with codec 0)
    codec_ref = Vector("the value this port last sent (the deadband's reference)")
    codec_rx = Vector("the value of the peer's last packet (its wave, or TDPA's x)")
    codec_sim_used = Vector("the peer's used wave energy as this sender predicts it, J")
    codec_sim_declared = Vector("the wave energy this port last declared, J")
    codec_e_sent = Vector("TDPA: the E_in this port last sent, J")
    codec_slope = Vector("the slope the peer extrapolates this port's last packet by, per tick")
    codec_rx_slope = Vector("the slope of the peer's last two packets, per tick")
    codec_rx_sum = Vector("TDPA: dt times the sum of the peer's values as reconstructed here")
    codec_debt = Vector("TDPA: the peer's x integral minus the one reconstructed, not yet paid")
    codec_e_crossed = Vector("TDPA: E_in + E_out of this port at its last packet sent, J")
    codec_flow = Vector("TDPA: energy crossing the port (in or out) per tick, low-passed over "
                        "codec.EXCHANGE_WINDOW_TICKS, J (the Weber rule's reference)")
    codec_crossed_last = Vector("TDPA: E_in + E_out of this port a tick ago, J")
    codec_ahead = Vector("the wave energy the peer declared in its newest packet that has "
                         "arrived but is not due yet, J (the link's look-ahead; 0: none)")
    codec_weber = Scalar("Weber fraction of the deadband", param=True)
    codec_floor = Scalar("its absolute floor, in the signal's units", param=True)
    codec_velocity_gain = Scalar("velocity-adaptive gain, s/rad (0: constant)", param=True)
    codec_reserve = Scalar("fraction of the band a wave is sent smaller by, when short", param=True)
    codec_room_ticks = Scalar("ticks of held wave the peer's room should cover", param=True)
    codec_energy_step = Scalar("TDPA: E_in grown by this since sent sends, J (0: off)", param=True)
    codec_exchange_step = Scalar("TDPA: energy crossed (in or out) since sent that sends, J "
                                 "(0: off)", param=True)
    codec_exchange_weber = Scalar("TDPA: the energy step grows by this fraction of the energy "
                                  "crossed over the last window (0: a fixed step)", param=True)
    codec_flow_alpha = Scalar("TDPA: the flow's low-pass coefficient, 1 / window", param=True)
    codec_predict = Scalar("1: the peer extrapolates this port's packets (linear); 0: holds",
                           param=True)  # fmt: skip
    codec_rx_predict = Scalar("the same for this port's reconstruction of the peer's", param=True)
    codec_sum_rate = Scalar("TDPA: the rate the reconstruction pays its debt at, 1/s", param=True)
    codec = Int("0: a packet every tick; 1: the deadband codec", param=True)
    codec_min = Int("the fewest ticks between two packets sent", param=True)
    codec_max = Int("the most ticks between two packets sent", param=True)
    codec_exchange_min = Int("TDPA: the energy deadband sends no sooner than this many ticks "
                             "after the last packet (1: at once)", param=True)
    codec_ahead_ticks = Int("the look-ahead the link gives the peer: a packet reaches it this "
                            "many ticks before it is due (0: none known); on ``reflected`` "
                            "also the hold cap (codec.REFLECT_HOLD_TICKS - 1 where none is "
                            "known)", param=True)
    codec_rx_seq = Int("sequence number of the peer's last packet (-1: none)")
    codec_since = Int("ticks since this port last sent")
    codec_age = Int("ticks since the peer's last packet")
    codec_sent = Int("packets sent")
    codec_by_threshold = Int("of which: the deadband crossed")
    codec_by_interval = Int("of which: the maximum interval up")
    codec_by_energy = Int("of which: the peer's energy room would run out")
    codec_silent = Int("ticks this port sent nothing")
    codec_held = Int("ticks with no packet from the peer, its last value held")
    codec_expired = Int("ticks with no packet past the maximum interval (a loss)")
    codec_engaged = Int("the coupling state of the last packet sent (a change is sent at once)")
    terminated = Int("1: the site is decoupled (teleop_rt.mapping): a matched damper b ends "
                     "the wave port, absorbing what arrives and sending no wave")

    def __init__(
        self,
        side: int,
        wave_impedance: list[float],
        delay_ticks: int,
        dt: float,
        mode: int = MODES[DEFAULT_MODE],
        filter_hz: float | None = None,
        reconstruction: int = RECONSTRUCTIONS[DEFAULT_RECONSTRUCTION],
        drift_time_s: float | None = None,
        wave_drift_time_s: float = WAVE_DRIFT_TIME_S,
        wave_skip_time_s: float | None = WAVE_SKIP_TIME_S,
        wave_impedance_schedule: bool = False,
        b_floor: float = WAVE_B_FLOOR,
        b_rate: float = WAVE_B_RATE,
    ) -> None:
        b = [float(x) for x in wave_impedance]
        if mode == WAVE and any(not x > 0 for x in b):
            raise ValueError("wave impedance b must be > 0 on every joint")
        require_delay_ticks(delay_ticks)
        super().__init__(len(b))
        self.side, self.mode, self.delay_ticks, self.dt = side, mode, delay_ticks, dt
        self.reconstruction = reconstruction
        self.last_seq = -1
        # each time constant T is paid back per tick as debt (1 - dt / T): below one tick that
        # overshoots, past two it grows without bound (inf, NaN in the ports)
        for what, t in (("drift compensation", drift_time_s),
                        ("wave drift correction", wave_drift_time_s),
                        ("skip debt", wave_skip_time_s)):  # fmt: skip
            if t is not None and not t >= dt:
                raise ValueError(f"the {what}'s time constant must be >= one tick ({dt:g} s)")
        self.drift_rate = 1.0 / drift_time_s if drift_time_s and side == TO else 0.0
        drifts = reconstruction in (CORRECTED, REFLECTED)
        self.wave_drift_rate = 1.0 / wave_drift_time_s if drifts else 0.0
        self.skip_rate = 1.0 / wave_skip_time_s if drifts and wave_skip_time_s else 0.0
        if mode == WAVE:
            self.b[:] = b
            self.sqrt_2b[:] = [math.sqrt(2.0 * x) for x in b]
            self.sqrt_2_over_b[:] = [math.sqrt(2.0 / x) for x in b]
            self.b_now[:], self.sqrt_2b_now[:] = self.b, self.sqrt_2b
            self.sqrt_2_over_b_now[:] = self.sqrt_2_over_b
        if not 0.0 < b_floor <= 1.0 or not b_rate > 0.0:
            raise ValueError("the scheduled b's floor must be in (0, 1] of b, its rate > 0")
        # (only a wave channel over a delay has waves to schedule)
        self.b_schedule = int(bool(wave_impedance_schedule) and mode == WAVE and delay_ticks > 0)
        self.b_floor, self.b_rate = b_floor, b_rate
        self.b_hold_ticks, self.age_floor = round(WAVE_B_HOLD_S / dt), -1
        # the filter acts on received waves; with no delay there are none (direct coupling)
        self.filter_hz = filter_hz if delay_ticks > 0 and mode == WAVE else None
        self.filtered = int(self.filter_hz is not None)
        self.alpha = 1.0
        if self.filter_hz:
            self.alpha = 1.0 - math.exp(-2.0 * math.pi * self.filter_hz * dt)

    def protection(self) -> dict:
        """What the channel's protection did at this port: its balance's minimum (J; < 0: the
        channel made energy, as the method accounts it), the ticks it acted in and the energy
        it removed (the bound's cut, or TDPA's dissipation, J)."""
        return {
            "min_balance_j": float(self.min_balance),
            "acted_ticks": int(self.acted),
            "removed_j": float(self.limited.sum()),
        }


@jit
def port_input(f: np.ndarray, i: np.ndarray, n: int, x: np.ndarray, tx: np.ndarray) -> None:
    """This tick's port input x (omega_c at the HSI, tau_t at the TO) into the port and into
    the outgoing packet (before the exchange: with no delay the peer needs it this tick)."""
    Pt, Pk = Port.idx, Packet.idx
    own = vec(f, Pt.FLOW, n) if i[Pt.SIDE] == HSI else vec(f, Pt.EFFORT, n)
    out = vec(tx, Pk.X, n)
    dt = f[Pt.N_VECTORS * n + Pt.DT]
    for j in range(n):
        own[j] = x[j]
        out[j] = x[j]
        f[Pt.X_SUM * n + j] += x[j] * dt
        tx[Pk.X_SUM * n + j] = f[Pt.X_SUM * n + j]


@jit
def port_step(
    f: np.ndarray, i: np.ndarray, n: int, rx: np.ndarray, rx_i: np.ndarray, tx: np.ndarray
) -> None:
    """The port's output from the received packet (rx, rx_i); the outgoing wave into tx; the
    power and energy that crossed the port."""
    Pt, Pk = Port.idx, Packet.idx
    valid = rx_i[Pk.VALID] != 0
    if valid:  # the peer's E_in: monotone, so the newest packet's is the largest
        for j in range(n):
            f[Pt.PEER_E_IN * n + j] = max(f[Pt.PEER_E_IN * n + j], rx[Pk.E_IN * n + j])
            f[Pt.PEER_X_SUM * n + j] = rx[Pk.X_SUM * n + j]
    if i[Pt.DELAY_TICKS] == 0 or i[Pt.MODE] == DIRECT:
        # direct coupling (no delay) or plain delayed force feedback: the peer's port input
        out = vec(f, Pt.EFFORT, n) if i[Pt.SIDE] == HSI else vec(f, Pt.FLOW, n)
        peer_x = vec(rx, Pk.X, n)
        for j in range(n):
            out[j] = peer_x[j]
    elif i[Pt.MODE] == TDPA:
        tdpa_step(f, i, n, rx, rx_i)
    else:
        wave_step(f, i, n, rx, rx_i, tx)
    if valid:
        i[Pt.LAST_SEQ] = rx_i[Pk.SEQ]
        i[Pt.MISSING] = 0
    else:
        i[Pt.MISSING] += 1
    account_port_power(f, i, n, tx)
    if i[Pt.DELAY_TICKS] > 0:
        account_balance(f, i, n)


@jit
def account_balance(f: np.ndarray, i: np.ndarray, n: int) -> None:
    """This port's energy balance as its method accounts it, the smallest over joints: a wave
    channel's wave energy received minus emitted; TDPA's (and, for comparison, the direct
    channel's) peer E_in received minus this port's E_out. Negative: the channel made energy."""
    Pt = Port.idx
    s = Pt.N_VECTORS * n
    if i[Pt.MODE] == WAVE:
        got, spent = Pt.GOT_ENERGY, Pt.USED_ENERGY
    else:
        got, spent = Pt.PEER_E_IN, Pt.E_OUT
    how = i[Pt.RECONSTRUCTION]
    bounded = i[Pt.MODE] == WAVE and (how == BOUNDED or how == CORRECTED)
    reflected = i[Pt.MODE] == WAVE and how == REFLECTED
    low = math.inf
    for j in range(n):
        if reflected:  # the room: budget and what was sent, less what was declared and used
            low = min(low, reflect_room(f, n, j))
        elif bounded:
            low = min(low, f[Pt.GOT_ENERGY * n + j] - charged(f, n, j))
        else:
            low = min(low, f[got * n + j] - f[spent * n + j])
    f[s + Pt.BALANCE] = low
    if not low >= f[s + Pt.MIN_BALANCE]:  # NaN counts as a new minimum
        f[s + Pt.MIN_BALANCE] = low


@jit
def charged(f: np.ndarray, n: int, j: int) -> float:
    """What the bound has charged to its budget, J: the energy of the waves it emitted into
    the received-wave filter while that is within the budget (the filter's output has no more:
    its output is a convex combination of its inputs), else the filter's output's own."""
    Pt = Port.idx
    used = f[Pt.USED_ENERGY * n + j]
    return used if used <= f[Pt.GOT_ENERGY * n + j] else f[Pt.OUT_ENERGY * n + j]


@jit
def reflect_room(f: np.ndarray, n: int, j: int) -> float:
    """``reflected``: what this port may still take out of the channel, J: the budget (the
    peer's declared energy that reached it) plus the wave energy it sent, less what it
    declared and what the filter gave it (>= 0; the two ports' rooms and declarations sum to
    the two-port's energy's lower bound, see ``wave_step``)."""
    Pt = Port.idx
    return (f[Pt.GOT_ENERGY * n + j] + f[Pt.WAVE_ENERGY * n + j] - f[Pt.DECLARED * n + j]
            - f[Pt.OUT_ENERGY * n + j])


@jit
def wave_step(
    f: np.ndarray, i: np.ndarray, n: int, rx: np.ndarray, rx_i: np.ndarray, tx: np.ndarray
) -> None:
    """Eq 9 on the received wave, reconstructed as the port's ``reconstruction`` says; the
    wave energy received in time and emitted, for every reconstruction (the balance)."""
    Pt, Pk = Port.idx, Packet.idx
    s = Pt.N_VECTORS * n
    alpha, filtered, dt = f[s + Pt.ALPHA], i[Pt.FILTERED] != 0, f[s + Pt.DT]
    half_dt = 0.5 * dt
    flow, effort = vec(f, Pt.FLOW, n), vec(f, Pt.EFFORT, n)
    w_in, w_out, received = vec(f, Pt.WAVE_IN, n), vec(f, Pt.WAVE_OUT, n), vec(rx, Pk.WAVE, n)
    held = vec(f, Pt.HELD, n)
    hsi, how, valid = i[Pt.SIDE] == HSI, i[Pt.RECONSTRUCTION], rx_i[Pk.VALID] != 0
    scheduled = i[Pt.B_SCHEDULE] != 0
    if scheduled:  # b scheduled by the delay: the transform at this tick's b
        schedule_b(f, i, n, rx_i)
        if not hsi:  # the position correction's window: while b is off b_0, and a while after
            moved = False
            for j in range(n):
                moved = moved or f[Pt.B_NOW * n + j] != f[Pt.B * n + j]
            if moved:
                if i[Pt.B_MOVED] == 0:
                    for j in range(n):
                        f[Pt.POS_REF * n + j] = f[Pt.PEER_X_SUM * n + j] - f[Pt.OUT_SUM * n + j]
                i[Pt.B_MOVED] = i[Pt.B_HOLD_TICKS]
            elif i[Pt.B_MOVED] > 0:
                i[Pt.B_MOVED] -= 1
        b, s2b = vec(f, Pt.B_NOW, n), vec(f, Pt.SQRT_2B_NOW, n)
        s2ob = vec(f, Pt.SQRT_2_OVER_B_NOW, n)
    else:
        b, s2b, s2ob = vec(f, Pt.B, n), vec(f, Pt.SQRT_2B, n), vec(f, Pt.SQRT_2_OVER_B, n)
    terminated = i[Pt.TERMINATED] != 0
    coded = i[Pt.CODEC] != 0  # the deadband codec (teleop_rt.com.codec) is on
    reflected = how == REFLECTED
    corrected = how == CORRECTED or reflected
    bounded = how == BOUNDED or corrected
    rate, skip_rate = f[s + Pt.WAVE_DRIFT_RATE], f[s + Pt.SKIP_RATE]
    missed = rx_i[Pk.SEQ] - i[Pt.LAST_SEQ] - 1  # packets missed since the last one used
    catch_up = valid and 0 < missed <= CATCH_UP
    # the delay changed under the ``newest`` playout: packets skipped with no silence (it
    # dropped: the sequence jumps while packets kept coming), or silent ticks with no packet
    # missed (it grew: a tick inserted); that share of a packet's new debt is a skip debt, an
    # outage's or a loss's (as many silent ticks as packets missed) is not; the first packet
    # closes no gap (the ticks before it are the delay's); off (skip_rate 0): one debt
    gap = max(missed, i[Pt.MISSING]) if skip_rate > 0 and valid and i[Pt.LAST_SEQ] >= 0 else 0
    skipped = abs(missed - i[Pt.MISSING]) if gap > 0 else 0
    # a held wave expires: after HOLD_TICKS ticks of silence the bound emits zeros and gives
    # up what it had left (energy that only a stale wave would spend)
    expired = bounded and not reflected and not valid and i[Pt.MISSING] >= HOLD_TICKS
    acted = synced = False
    for j in range(n):
        used_sum = f[Pt.USED_SUM * n + j]
        pos = 0.0  # the position correction's part of the wave used
        r = received[j]
        e_r = r * r * half_dt  # (the term the sender added to its wave energy, bit for bit)
        if valid:
            # in step: nothing missed and the integral as the peer's; after a long gap the
            # integral is not caught up (a jolt), only taken as it is
            synced = (missed == 0 and used_sum == f[Pt.PEER_SUM * n + j]) or missed > CATCH_UP
            # honest credit: this sample's energy, and in a catch-up that of the samples it
            # catches up (known from the peer's cumulative energy); after a long gap the
            # skipped samples' energy is not credited: they never reached this port
            # (with the deadband codec a held tick repeats the declared energy and the next
            # packet brings the energy of the samples sent while silent: credit what the peer
            # declared, never the held sample's own)
            got = f[Pt.GOT_ENERGY * n + j]
            if bounded and (missed > 0 or coded):
                f[Pt.GOT_ENERGY * n + j] += rx[Pk.WAVE_ENERGY * n + j] - f[Pt.PEER_ENERGY * n + j]
            else:
                f[Pt.GOT_ENERGY * n + j] += e_r
            if reflected:  # what the peer declared (monotone: a reordered packet's is less)
                f[Pt.GOT_ENERGY * n + j] = max(got, rx[Pk.WAVE_ENERGY * n + j])
            f[Pt.PEER_SUM * n + j] = rx[Pk.WAVE_SUM * n + j]
            f[Pt.PEER_ENERGY * n + j] = rx[Pk.WAVE_ENERGY * n + j]
        debt = f[Pt.DEBT * n + j]
        paid = 0.0  # this tick's pay-back of the debt, per second (the gap's share leaves it out)
        if reflected and not valid and i[Pt.LAST_SEQ] >= 0:  # (before the first: zeros)
            # the TO brakes: the wave that gives omega_t = 0, u_r = tau_t / sqrt(2b), all of it
            # reflected (zero power, whatever the contact); the HSI holds the TO's effort of
            # its last packet, tau_c = tau_t: v_l = (b omega_c - tau_t) / sqrt(2b) (a static
            # push is felt as it was; its wave integral is that of the braked TO's: the
            # drift correction then moves the TO by what the HSI moved, no more)
            w = (b[j] * flow[j] - held[j]) / s2b[j] if hsi else effort[j] / s2b[j]
            if filtered:
                w = w_in[j] + (w - w_in[j]) / alpha  # (what the filter then gives the port)
        elif corrected and valid:
            # the samples this packet brings (in a catch-up: those missed, less what a hold
            # emitted for them, and this one), plus a part of the debt: the integral the bound
            # cut or an outage lost, paid back within the budget (Niemeyer & Slotine 2004)
            w = (f[Pt.PEER_SUM * n + j] - used_sum - debt) / dt if catch_up else r
            if debt != 0.0:
                slow = f[Pt.SKIP_DEBT * n + j]
                if slow == 0.0:
                    paid = rate * debt
                else:  # the skip debt at its own rate, the rest at the drift correction's
                    pay = skip_rate * slow
                    paid = rate * (debt - slow) + pay
                    f[Pt.SKIP_DEBT * n + j] = slow - pay * dt
                w += paid
        elif how == ZERO or (valid and (how == HOLD or synced)):
            w = r  # (zero: zeros when none arrived; else the wave as it was sent)
        elif not valid:
            w = 0.0 if expired else held[j]
        else:  # catch the integral up in this tick: the samples missed and this one
            w = (f[Pt.PEER_SUM * n + j] - used_sum) / dt
        if scheduled and not hsi and i[Pt.B_MOVED] > 0:
            # b moving with the delay scales a wave decoded at another b than it was encoded
            # with (the TO's velocity sqrt(b_h / b_t) the HSI's): position drift that the wave
            # integral does not see; so the TO moves toward the HSI's position as of its newest
            # packet at the drift correction's rate (d omega_t = sqrt(2 / b) d u_r), within
            # the budget below (position tracking with wave variables: Chopra, Spong, Hirche &
            # Buss, ACC 2003)
            # (not counted in the integral used: the wave integral's debt would undo it)
            pos = rate * 0.5 * s2b[j] * (f[Pt.PEER_X_SUM * n + j] - f[Pt.OUT_SUM * n + j]
                                         - f[Pt.POS_REF * n + j])
            w += pos
        e = w * w * half_dt
        got = f[Pt.GOT_ENERGY * n + j]
        w_save = w
        # emit no more wave energy than reached this port in time (compared as the sums
        # themselves: with the same waves in the same order they are equal, bit for bit);
        # with the filter, what counts is what the filter gives the port: a held wave may
        # spend the energy the filter's lag left unspent (about 1.5 / alpha samples' worth of
        # a steady wave), which the catch-up's skipped samples then pay back
        if reflected:
            w = reflect_bound(f, n, j, w, w_in[j], alpha, filtered, half_dt,
                              s2b[j] * flow[j] if hsi else s2ob[j] * effort[j], terminated)
            if w != w_save:
                acted = True
            e = w * w * half_dt
        elif bounded and f[Pt.USED_ENERGY * n + j] + e > got:
            acted = True  # (engaged: what the filter gives the port is checked, cut if need be)
            room = max(got - f[Pt.OUT_ENERGY * n + j], 0.0)
            y = w_in[j] + alpha * (w - w_in[j]) if filtered else w
            e_y = y * y * half_dt
            if f[Pt.OUT_ENERGY * n + j] + e_y > got:
                y_c = math.copysign(min(abs(y), math.sqrt(room / half_dt)), y)
                f[Pt.LIMITED * n + j] += e_y - y_c * y_c * half_dt
                w = w_in[j] + (y_c - w_in[j]) / alpha if filtered else y_c
                e = w * w * half_dt
        f[Pt.USED_ENERGY * n + j] += e
        y = w_in[j] + alpha * (w - w_in[j]) if filtered else w  # what the filter gives the port
        if bounded and not reflected and (expired or (valid and missed > 0)):
            # what a catch-up did not spend of the skipped samples' energy is not kept beyond
            # the budget left after the last packet and this sample's; an expired hold keeps
            # only the energy the filter holds ((1 - alpha) / alpha y^2 dt / 2: what received
            # waves may still draw out of it, Jensen), nothing for a stale wave
            if expired:
                keep = (1.0 - alpha) / alpha * y * y * half_dt if filtered else 0.0
                out = f[Pt.OUT_ENERGY * n + j] + y * y * half_dt
                f[Pt.GOT_ENERGY * n + j] = min(got, out + keep)
            else:
                keep = f[Pt.BANKED * n + j] + (e_r if catch_up else 0.0)
                spent = f[Pt.USED_ENERGY * n + j]
                if spent > got:
                    spent = f[Pt.OUT_ENERGY * n + j] + y * y * half_dt
                f[Pt.GOT_ENERGY * n + j] = min(got, spent + keep)
        # in step with the peer's integral after a packet (what the bound cut is not caught
        # up later: that would need energy the peer did not send)
        if corrected:  # the integral as used, and what it owes after a packet
            f[Pt.USED_SUM * n + j] = used_sum + (w - pos) * dt
            if valid:
                f[Pt.DEBT * n + j] = f[Pt.PEER_SUM * n + j] - f[Pt.USED_SUM * n + j]
                if skipped > 0:  # the skipped packets' share of what this gap added: the
                    # debt beyond what is left of the last after this tick's pay-back (the
                    # skip debt has had its own; the rest of the debt keeps its rate)
                    added = f[Pt.DEBT * n + j] - (debt - paid * dt)
                    f[Pt.SKIP_DEBT * n + j] += skipped / gap * added
                slow = f[Pt.SKIP_DEBT * n + j]
                if slow != 0.0:  # never more than the debt, nor of the other sign
                    total = f[Pt.DEBT * n + j]
                    if slow * total <= 0.0:
                        f[Pt.SKIP_DEBT * n + j] = 0.0
                    elif abs(slow) > abs(total):
                        f[Pt.SKIP_DEBT * n + j] = total
        else:
            f[Pt.USED_SUM * n + j] = f[Pt.PEER_SUM * n + j] if valid else used_sum + w * dt
        if not bounded:
            held[j] = w
        elif reflected and hsi and valid:
            held[j] = rx[Pk.X * n + j]  # the TO's effort
        elif valid:
            held[j] = r  # the sample as it arrived (not a catch-up's sum, nor the bound's cut)
        w_in[j] = y
        f[Pt.OUT_ENERGY * n + j] += y * y * half_dt
        if bounded and valid and not reflected:
            f[Pt.BANKED * n + j] = f[Pt.GOT_ENERGY * n + j] - charged(f, n, j)
        if terminated:  # a matched damper: omega = w_in / sqrt(2b), tau = -+ b omega, no wave
            flow[j] = w_in[j] / s2b[j]
            effort[j] = -b[j] * flow[j] if hsi else b[j] * flow[j]
            w_out[j] = 0.0
        elif hsi:  # tau_c = b omega_c - sqrt(2b) v_l ; u_l = sqrt(2b) omega_c - v_l
            effort[j] = b[j] * flow[j] - s2b[j] * w_in[j]
            w_out[j] = s2b[j] * flow[j] - w_in[j]
        else:  # omega_t = (sqrt(2b) u_r - tau_t) / b ; v_r = u_r - sqrt(2/b) tau_t
            flow[j] = (s2b[j] * w_in[j] - effort[j]) / b[j]
            w_out[j] = w_in[j] - s2ob[j] * effort[j]
            if scheduled:
                f[Pt.OUT_SUM * n + j] += flow[j] * dt  # (its position, for the correction)
        sent = w_out[j]
        tx[Pk.WAVE * n + j] = sent
        f[Pt.WAVE_SUM * n + j] += sent * dt
        f[Pt.WAVE_ENERGY * n + j] += sent * sent * half_dt
        tx[Pk.WAVE_SUM * n + j] = f[Pt.WAVE_SUM * n + j]
        if reflected:
            # declared: what was sent, less what this port used beyond its budget (its debt
            # moves to the peer's budget; monotone, so a late or reordered packet's is never
            # more than today's)
            debt_e = min(0.0, f[Pt.GOT_ENERGY * n + j] - f[Pt.OUT_ENERGY * n + j])
            f[Pt.DECLARED * n + j] = max(f[Pt.DECLARED * n + j], f[Pt.WAVE_ENERGY * n + j] + debt_e)
            tx[Pk.WAVE_ENERGY * n + j] = f[Pt.DECLARED * n + j]
        else:
            tx[Pk.WAVE_ENERGY * n + j] = f[Pt.WAVE_ENERGY * n + j]
    if acted:
        i[Pt.ACTED] += 1


@jit
def schedule_b(f: np.ndarray, i: np.ndarray, n: int, rx_i: np.ndarray) -> None:
    """The wave impedance scheduled by the delay this port measures: a packet's age
    a = now - its sender tick (ticks; >= D, the playout delay, under either playout rule; over
    a network it also holds the sites' tick offset, 0 in one process as in the study) sets the
    target b_0 min(1, max(floor, a_min / a)), so that the wave channel's free-space inertia,
    about b T at one-way delay T, stays about the clean link's b_0 a_min; b moves toward it
    by at most ``b_rate`` b_0 per second, and is held on ticks with no packet (no new age).
    Passive by construction: the transform at each port conserves power for whatever b > 0
    it uses in that tick (omega tau = (u^2 - v^2) / 2 at that b), so the wave energies the
    budgets count are the port's energy at any schedule; what changes is only the impedance
    displayed: b tanh(sT), an inertia about b T in free space, a stiffness
    about b / T against a wall (Niemeyer & Slotine, IEEE JOE 1991, on b as the tuning knob; a
    b switched between a low free-motion and a high contact value, passive under
    time-varying delay: J. Robotics 2015, article 861425, hindawi.com/journals/jr/2015/861425,
    found by its abstract, its scheme not checked against this one; Lozano, Chopra & Spong's
    time-varying-delay wave gain, 2002, which the search did not find and this does not use).
    The reference a_min is the least age used so far (the path's own floor: the clean link's
    delay as this port can know it), so a clean link's b is b_0 bit for bit."""
    Pt, Pk = Port.idx, Packet.idx
    if rx_i[Pk.VALID] == 0:
        return
    s = Pt.N_VECTORS * n
    age = i[Pt.NOW_TICK] - rx_i[Pk.TICK]
    if i[Pt.AGE_FLOOR] < 0 or age < i[Pt.AGE_FLOOR]:
        i[Pt.AGE_FLOOR] = max(age, 1)
    d = i[Pt.AGE_FLOOR]
    share = 1.0 if age <= d else max(f[s + Pt.B_FLOOR], d / age)
    step = f[s + Pt.B_RATE] * f[s + Pt.DT]
    for j in range(n):
        b0, now = f[Pt.B * n + j], f[Pt.B_NOW * n + j]
        target = b0 * share
        if target == now:
            continue
        new = min(max(target, now - step * b0), now + step * b0)
        if new >= b0:  # back at b_0: its own transform, bit for bit
            f[Pt.B_NOW * n + j] = b0
            f[Pt.SQRT_2B_NOW * n + j] = f[Pt.SQRT_2B * n + j]
            f[Pt.SQRT_2_OVER_B_NOW * n + j] = f[Pt.SQRT_2_OVER_B * n + j]
        else:
            f[Pt.B_NOW * n + j] = new
            f[Pt.SQRT_2B_NOW * n + j] = math.sqrt(2.0 * new)
            f[Pt.SQRT_2_OVER_B_NOW * n + j] = math.sqrt(2.0 / new)


@jit
def reflect_bound(
    f: np.ndarray, n: int, j: int, w: float, w_in: float, alpha: float, filtered: bool,
    half_dt: float, c: float, terminated: bool,
) -> float:  # fmt: skip
    """``reflected``'s bound: the wave w, cut so that the energy this tick takes out of the
    channel at this port is within its room. With y what the filter gives the port and c the
    port input's part of the outgoing wave (sqrt(2b) omega_c at the HSI, sent c - y;
    sqrt(2/b) tau_t at the TO, sent y - c), that energy is (y^2 - (y - c)^2) dt / 2 =
    (2 y c - c^2) dt / 2: linear in y, so the cut is y c = (room / (dt/2) + c^2) / 2 (a
    terminated port sends nothing: |y| is cut to the room). Energy this port reflects back to
    the peer pays for what it emits beyond the peer's budget, and ``declared`` removes it from
    what the peer may spend: the two-port stays passive."""
    Pt = Port.idx
    room = max(reflect_room(f, n, j), 0.0)
    y = w_in + alpha * (w - w_in) if filtered else w
    if terminated:
        if y * y * half_dt <= room:
            return w
        y_c = math.copysign(math.sqrt(room / half_dt), y)
        f[Pt.LIMITED * n + j] += y * y * half_dt - room
    else:
        top = room / half_dt + c * c
        if 2.0 * y * c <= top:
            return w
        y_c = top / (2.0 * c)
        f[Pt.LIMITED * n + j] += (2.0 * y * c - top) * half_dt
    return w_in + (y_c - w_in) / alpha if filtered else y_c


@jit
def tdpa_step(f: np.ndarray, i: np.ndarray, n: int, rx: np.ndarray, rx_i: np.ndarray) -> None:
    """The peer's delayed port input (held through a gap of up to ``HOLD_TICKS``, then zero: a
    held velocity would drive the TO on for as long as the gap lasts), then the passivity
    controller: this port's E_out may not exceed the peer's E_in received so far."""
    Pt, Pk = Port.idx, Packet.idx
    s = Pt.N_VECTORS * n
    dt, rate = f[s + Pt.DT], f[s + Pt.DRIFT_RATE]
    flow, effort, held = vec(f, Pt.FLOW, n), vec(f, Pt.EFFORT, n), vec(f, Pt.HELD, n)
    e_out, peer_e_in, limited = vec(f, Pt.E_OUT, n), vec(f, Pt.PEER_E_IN, n), vec(f, Pt.LIMITED, n)
    hsi, valid = i[Pt.SIDE] == HSI, rx_i[Pk.VALID] != 0
    acted = False
    expired = not valid and i[Pt.MISSING] >= HOLD_TICKS
    for j in range(n):
        if valid:
            held[j] = rx[Pk.X * n + j]
        elif expired:
            held[j] = 0.0
        if hsi:
            omega, tau = flow[j], held[j]
            out = -omega * tau * dt  # energy this tick's output takes out of the channel
        else:
            omega, tau = held[j], effort[j]
            # position drift: toward the HSI's position as of its newest packet (an output of
            # the peer's velocity as it was sent adds exactly 0, bit for bit); the passivity
            # controller below then checks the energy of the sum
            omega += rate * (f[Pt.PEER_X_SUM * n + j] - (f[Pt.OUT_SUM * n + j] + omega * dt))
            out = omega * tau * dt
        excess = min(e_out[j] + out - peer_e_in[j], out)
        if out > 0.0 and excess > 0.0:
            if hsi:  # impedance type: a damper on the HSI's velocity, tau_c += beta omega_c
                tau += excess / (omega * dt)
            else:  # admittance type: omega_t -= alpha tau_t
                omega -= excess / (tau * dt)
            limited[j] += excess
            acted = True
        if hsi:
            effort[j] = tau
        else:
            flow[j] = omega
            f[Pt.OUT_SUM * n + j] += omega * dt
    if acted:
        i[Pt.ACTED] += 1


@jit
def account_port_power(f: np.ndarray, i: np.ndarray, n: int, tx: np.ndarray) -> None:
    """Power into the channel at this port (omega_c tau_c, or -omega_t tau_t), its integral,
    the energy that entered and left (E_in, E_out), and the energies in the outgoing packet."""
    Pt, Pk = Port.idx, Packet.idx
    flow, effort = vec(f, Pt.FLOW, n), vec(f, Pt.EFFORT, n)
    power, energy = vec(f, Pt.POWER, n), vec(f, Pt.ENERGY, n)
    e_in, e_out = vec(f, Pt.E_IN, n), vec(f, Pt.E_OUT, n)
    s = Pt.N_VECTORS * n
    dt, sign = f[s + Pt.DT], 1.0 if i[Pt.SIDE] == HSI else -1.0
    total = 0.0
    for j in range(n):
        p = sign * flow[j] * effort[j]
        power[j] = p
        energy[j] += p * dt
        total += energy[j]
        if p > 0.0:
            e_in[j] += p * dt
        else:
            e_out[j] -= p * dt
        tx[Pk.E_IN * n + j] = e_in[j]
        tx[Pk.E_OUT * n + j] = e_out[j]
    f[s + Pt.TOTAL_ENERGY] = total
    tx[Pk.N_VECTORS * n + Pk.ENERGY] = total
