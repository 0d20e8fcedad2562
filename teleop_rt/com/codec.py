"""The perceptual deadband codec: a site sends a packet only when its signal has changed by
more than a person could feel, and the peer holds the last one passively in between.

Sender (``codec_send``, after the port has computed this tick's packet): the signal is the
port's outgoing wave on a wave channel (the deadband on wave variables: Kuschel, Kremer & Buss,
"Passive haptic data-compression methods with perceptual coding for bilateral presence
systems", IEEE Trans. SMC-A 39(6), 2009), TDPA's port input otherwise (the HSI's velocity,
the TO's torque, with the energy observers' E_in in every packet sent: Xu, Schuwerk, Cizmeci
& Steinbach, "Energy prediction for teleoperation systems that combine the time domain
passivity approach with perceptual deadband-based haptic data reduction", IEEE ToH 9(4),
2016). A packet goes out when, on any joint, ``|x - x_sent| > k |x_sent| + floor`` (Weber's
law: Hinterseer & Steinbach, HAPTICS 2006; the floor keeps zero crossings from sending every
tick), with ``k = weber (1 + gain |omega|)`` when velocity-adaptive (Kammerl et al., Presence
19(5), 2010: the just-noticeable difference of force grows with the hand's velocity); no
sooner than the minimum interval after the last one, and at the latest when the maximum
interval is up. A tick it does not send is a packet marked ``unsent``: the links carry nothing
(the peer's port sees a tick with no packet).

Receiver (``codec_receive``, before the port): a tick with no packet within the maximum
interval is the codec's silence, not a loss: the peer's last packet is used again, with the
energy it declared. What keeps that passive is the port's own rule, unchanged:

- wave channel on ``reflected`` (the codec's default): the held wave goes through that
  reconstruction's bound: beyond what the peer declared a port emits only what it reflects
  back, taken off what it declares in turn (``teleop_rt.com.port``). Its sender then needs no
  reserve and no model of the peer's room (below): it sends at the latest every
  ``REFLECT_HOLD_TICKS`` ticks (A + 1 with a look-ahead A); a real packet after held ticks is
  handed to the port as the next in line (no one-tick catch-up of the hold's integral error:
  under jitter that jolt was a velocity command the TO could not follow; docs/codec.md).
- wave channel on ``bounded``: the held wave goes through the energy bound:
  the wave energy this port emits never exceeds what the peer has declared sent, and the
  peer declares its TRUE wave energy, dt/2 sum u^2 over every tick, sent or not. Why not the
  energy of the held wave it knows the receiver uses (the tempting choice: the receiver's
  balance would then close exactly): the channel's energy (eq 7) is what the sender's port put
  in, dt/2 sum u^2, minus what the receiver emits, dt/2 sum u_hold^2; inside the deadband
  |u| may sit below |u_hold| by up to k / (1 + k) for the whole interval, so the held wave
  emits up to 1 / (1 - k)^2 - 1 (23 % at k = 0.1) more than entered and the two-port makes
  energy. Declaring the true energy makes the hold passive under any loss, delay or
  reordering (the bound's argument: emitted <= declared <= put in).
- Its cost: the receiver's energy room lags one interval (the declaration is as of the last
  packet). So the sender also predicts the receiver's bound (lossless: it knows what it sent
  and that the receiver holds it) and sends as soon as the held wave would not fit in the
  room it declared (``by_energy``): the receiver then never cuts a wave the sender knows of.
  That alone would send nearly every tick: in a steady state (a constant push) the room
  is only what the receiver has used less than declared, and holding a wave equal to the
  true one builds none. So a wave sent while the room after it would not hold it
  ``ROOM_TICKS`` ticks is sent ``RESERVE`` of the band smaller (|u - u_sent| stays inside the
  band): holding it then uses less than the sender puts in, and the room builds up to let
  the intervals grow (the price: a held wave up to 8 % of its size low, at k = 0.1, until the
  room is there; docs/codec.md has the trade-off measured).
- The look-ahead of the room (``codec_line_ahead``): where the link hands packets over before
  they are due (the in-process link: at once, played D ticks later), the receiver's budget
  counts the energy declared by the newest packet that has arrived, due or not: energy the
  peer has really sent, and credited as the increment over the last declaration counted
  (monotone), so never twice. A sender told the link's look-ahead A (``look_ahead``) then
  models the peer's room at each tick as its true wave energy so far, sends at the latest
  every A + 1 ticks (so that a declaration covering it arrives in time) and needs no
  reserve: no bank to build. Its model of the peer's use is then uncut (at most what the
  peer uses); a network slower than assumed costs transparency (the bound cuts), never
  passivity.
- TDPA: the held velocity or torque through the passivity controller, against the peer's
  E_in of its last packet: the controller dissipates whatever the held value would emit
  beyond it (Xu et al. 2016: the observers' energy travels with the samples). Since that
  E_in is stale between packets, a port also sends once its E_in has grown by
  ``ENERGY_STEP_J`` since its last packet (``by_energy``): less for the controller to
  dissipate that the peer had put in. Xu et al. predict the peer's energy between packets
  instead, so that the controller is less conservative; not built: at D = 1 ms on the stiff
  wall the E_in kept fresh to 1e-7 J (this trigger: as fresh as a prediction could make it)
  leaves the felt stiffness as far off (-42 %), and a prediction that runs above a lost
  correction is not passive (docs/codec.md).
- TDPA's energy deadband (``exchange_j``, off by default; our own): a port also sends once
  more than that much energy has crossed it, in or out, since its last packet. Where energy
  flows (contact) the hold stays short: at D = 1 ms the hold's lag is what costs the stiff
  wall's felt stiffness (the channel without codec loses 23 % of it from 1 to 2 ms of
  delay; the codec's holds drove a sustained oscillation there whose passivity-controller
  cuts drifted the TO out of the wall). Free motion and a settled push cross little energy
  and keep the deadband's intervals. It only adds packets: passive as before.
  With ``exchange_weber`` w (off by default; our own, after Weber's law as the deadband
  itself applies it: Hinterseer & Steinbach 2006) the step grows by w times the NET energy
  that crossed the port over the last ``EXCHANGE_WINDOW_TICKS`` (a low-pass of E_in - E_out
  per tick): a steady flow one way (foam's damping in a push) then sends a packet per
  w N ticks or so instead of per step, while an oscillation's energy, which goes back and
  forth and nets about zero, keeps the fixed step (the stiff wall's limit cycle at D = 1 ms;
  the gross flow as the reference brings it back: measured, docs/codec.md). A trigger only.
  With ``exchange_min_ticks`` m (1 by default: off; our own) the energy deadband sends no
  sooner than m ticks after the last packet (the deadband's own crossings still go out at
  once: unlike ``min_interval_ticks`` it spaces only the energy's packets). Why (tick traces
  of the stiff wall at D = 1 ms, docs/codec.md): in the settled push the holds leave a
  ~22 Hz limit cycle inside the Weber band (0.007 rad/s at the HSI, +-0.03 N m of a 1.9 N m
  push), and the push's force times that velocity crosses ~1e-5 J a tick, so a step of
  2e-5 J fires in bursts wherever the cycle moves, 27 % of the push's ticks, all by energy.
  A small step with a pace of 3 samples the cycle at a steady 3-4 ticks instead, which damps
  it (7e-6 J: 0.0036 -> 0.0012 rad/s RMS) and sends fewer (23 %). A trigger only: passive.

Past the maximum interval the peer should have sent: the tick is a loss (``expired``) and the
port's own loss rule applies (the bounded hold, TDPA's hold then zero); the peer timeout
counts the maximum interval too (``teleop_rt.com.zenoh_link``).
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.link import LF, LI, InProcessLink, entry_size, packet_floats
from teleop_rt.com.port import WAVE, Packet, Port
from teleop_rt.declarations import (
    EXCHANGE_J,
    EXCHANGE_MIN_TICKS,
    EXCHANGE_WEBER,
    REFLECTED,
    VELOCITY_GAIN_S_PER_RAD,
    deadband_problem,
)
from teleop_rt.flat import jit

NONE, DEADBAND = 0, 1
# a wave sent while the peer's room is short is this fraction of the band smaller (below
# 1 / (1 + weber): the true wave is still inside the band around it)
RESERVE = 0.8
ROOM_TICKS = 5.0  # ... while the room after it would not hold it this many ticks
# ... with a look-ahead (each tick's energy is declared in time: no bank needs building)
AHEAD_ROOM_TICKS = 0.0
# the look-ahead A a sender counts on: at most this fraction of D (the rest: the network's
# margin) and this many ticks; it sends at the latest every A + 1 ticks, which also bounds
# the hold's error (measured: 8 keeps T_p and T_tau within 10 % at >= 85 % reduction at 20
# and 50 ms; docs/codec.md)
AHEAD_FRACTION, AHEAD_TICKS = 0.4, 8
# ``reflected`` (the wave channel's default with the codec): the peer's port may emit a held
# wave beyond what was declared as long as it reflects the energy back (taken off what it
# declares), so a sender needs neither the reserve nor a model of the peer's room; it sends at
# the latest this many ticks after its last packet where no look-ahead is known (D = 1 tick,
# the impaired link, Zenoh), which bounds the hold's lag (measured on the stiff wall at
# D = 1 ms: 7 ticks -5 % felt stiffness at 85.6 % reduction, 8 ticks -10 %; docs/codec.md)
REFLECT_HOLD_TICKS = 7
# TDPA's energy deadband with ``exchange_weber``: the window its reference flow is low-passed
# over (the step grows by exchange_weber times the energy crossed in about this many ticks)
EXCHANGE_WINDOW_TICKS = 100
ENERGY_STEP_J = 1e-4  # TDPA: a port whose E_in grew by this since its last packet sends
CODECS = {"none": NONE, "deadband": DEADBAND}
# TDPA: the reconstruction pays the peer's integral back (its position, or its torque's
# impulse) with this time constant (measured: 50 ms leaves +5 % T_p at 20 ms, 20 ms +1.4 %)
SUM_TIME_S = 0.02
PREDICTIONS = {"hold": 0.0, "linear": 1.0}
# how the peer reconstructs the HSI's and the TO's packets, by channel mode: measured best
# (docs/codec_study.md): the wave channel extrapolates the HSI's wave (both ways linear
# halves the displayed mass in free space), TDPA the TO's torque (the HSI's velocity is
# integrated into position, which the integral reconstruction keeps)
PREDICTIONS_BY_MODE = {"wave": ("linear", "hold"), "tdpa": ("hold", "linear")}


def configure(
    port: Port, weber: float, floor: float, min_ticks: int, max_ticks: int,
    velocity_gain: float = VELOCITY_GAIN_S_PER_RAD, prediction: str = "linear",
    peer_prediction: str | None = None,
    exchange_j: float = EXCHANGE_J, exchange_weber: float = EXCHANGE_WEBER,
    exchange_min_ticks: int = EXCHANGE_MIN_TICKS,
) -> None:  # fmt: skip
    """Switch the deadband codec on at ``port`` (its own signal's Weber fraction and floor;
    ``prediction``: how the peer reconstructs this port's packets between them, 'linear' or
    'hold'; ``peer_prediction``: how this port reconstructs the peer's, default the same)."""
    peer_prediction = prediction if peer_prediction is None else peer_prediction
    if prediction not in PREDICTIONS or peer_prediction not in PREDICTIONS:
        raise ValueError(f"the codec's prediction is one of {sorted(PREDICTIONS)}")
    # (called without a config too: the rules, and their numbers, are the config's own)
    problem = deadband_problem(weber, floor, min_ticks, max_ticks, velocity_gain, exchange_j,
                               exchange_weber, exchange_min_ticks)  # fmt: skip
    if problem:
        raise ValueError(f"the deadband codec: {problem}")
    if exchange_j > 0.0 and int(port.mode) == WAVE:
        raise ValueError("the codec's exchange_j is only for TDPA")
    if port.delay_ticks < 1:
        raise ValueError("the codec needs a delay of at least one tick")
    port.codec = DEADBAND
    port.codec_weber, port.codec_floor, port.codec_velocity_gain = weber, floor, velocity_gain
    port.codec_min, port.codec_max = min_ticks, max_ticks
    port.codec_reserve, port.codec_room_ticks = RESERVE, ROOM_TICKS
    port.codec_energy_step = ENERGY_STEP_J
    port.codec_exchange_step = exchange_j
    port.codec_exchange_weber = exchange_weber
    port.codec_flow_alpha = 1.0 / EXCHANGE_WINDOW_TICKS
    port.codec_exchange_min = exchange_min_ticks
    port.codec_predict = PREDICTIONS[prediction]
    port.codec_rx_predict = PREDICTIONS[peer_prediction]
    port.codec_sum_rate = 1.0 / SUM_TIME_S
    port.codec_rx_seq = -1
    look_ahead(port, 0)


def _reflects(port: Port) -> bool:
    return int(port.mode) == WAVE and int(port.reconstruction) == REFLECTED


def look_ahead(port: Port, ticks: int) -> None:
    """Tell ``port``'s sender that the link hands the peer each packet ``ticks`` ticks before
    it is due (the in-process link: D - 1; 0: no look-ahead known, the sender assumes none)."""
    if ticks < 0:
        raise ValueError("the codec's look-ahead is >= 0 ticks")
    if _reflects(port):
        # no bank to build, no room to model: the sender holds at most A + 1 ticks, A the
        # look-ahead or, with none, REFLECT_HOLD_TICKS - 1 (codec_send's uncut model)
        port.codec_ahead_ticks = ticks or REFLECT_HOLD_TICKS - 1
        port.codec_reserve, port.codec_room_ticks = 0.0, 0.0
        return
    port.codec_ahead_ticks = ticks
    port.codec_room_ticks = AHEAD_ROOM_TICKS if ticks else ROOM_TICKS


def ahead_ticks(delay_ticks: int) -> int:
    """The look-ahead a sender counts on over a link that hands packets over at once and
    plays them ``delay_ticks`` later: ``AHEAD_FRACTION`` of it, at most ``AHEAD_TICKS``."""
    return min(int(AHEAD_FRACTION * delay_ticks), AHEAD_TICKS)


def figures(port: Port) -> dict:
    """What the codec did at ``port``: packets sent, their rate and the reduction against one
    a tick, why they were sent, and the peer's silences held or lost."""
    sent = int(port.codec_sent)
    ticks, dt = sent + int(port.codec_silent), port.dt
    return {
        "sent": sent,
        "rate_hz": sent / (ticks * dt) if ticks else 0.0,
        "reduction": 1.0 - sent / ticks if ticks else 0.0,
        "by_threshold": int(port.codec_by_threshold),
        "by_max_interval": int(port.codec_by_interval),
        "by_energy": int(port.codec_by_energy),
        "silent_ticks": int(port.codec_silent),
        "peer_held_ticks": int(port.codec_held),
        "peer_expired_ticks": int(port.codec_expired),
    }


def predictions(mode: str, of_hsi: str | None, of_to: str | None) -> tuple[str, str]:
    """How the peer reconstructs the HSI's and the TO's packets: as given, else the mode's."""
    hsi, to = PREDICTIONS_BY_MODE[mode]
    return of_hsi or hsi, of_to or to


@jit
def codec_receive(f: np.ndarray, i: np.ndarray, n: int, rx: np.ndarray, rx_i: np.ndarray) -> None:
    """Before the port: a tick with no packet within the maximum interval since the peer's
    last one gets that packet again (its value, the energy it declared), for the port's own
    passivity rule to hold it; past the interval the tick stays a loss."""
    Pt, Pk = Port.idx, Packet.idx
    if i[Pt.CODEC] == NONE or i[Pt.DELAY_TICKS] == 0:
        return
    wave = i[Pt.MODE] == WAVE
    sig = Pk.WAVE if wave else Pk.X
    s = Pt.N_VECTORS * n
    dt = f[s + Pt.DT]
    rate = f[s + Pt.CODEC_SUM_RATE]
    if rx_i[Pk.VALID] != 0:
        gap = rx_i[Pk.SEQ] - i[Pt.CODEC_RX_SEQ]
        for j in range(n):
            r = rx[sig * n + j]
            slope = 0.0
            if i[Pt.CODEC_RX_SEQ] >= 0 and gap > 0:
                slope = f[s + Pt.CODEC_RX_PREDICT] * (r - f[Pt.CODEC_RX * n + j]) / gap
            f[Pt.CODEC_RX_SLOPE * n + j] = slope
            f[Pt.CODEC_RX * n + j] = r
            if not wave and rate > 0.0:
                # what the reconstruction so far missed of the peer's integral, this packet's
                # sample included; a part of it paid back now, the rest over the next ticks
                debt = rx[Pk.X_SUM * n + j] - f[Pt.CODEC_RX_SUM * n + j] - r * dt
                pay = rate * debt * dt
                rx[sig * n + j] = r + pay / dt
                f[Pt.CODEC_RX_SUM * n + j] = rx[Pk.X_SUM * n + j] - debt + pay
                f[Pt.CODEC_DEBT * n + j] = debt - pay
            if wave:  # the newest declared energy that has arrived, the look-ahead included
                # (monotone: the port credits the increment over the last, never one twice)
                e = max(rx[Pk.WAVE_ENERGY * n + j], f[Pt.CODEC_AHEAD * n + j])
                rx[Pk.WAVE_ENERGY * n + j] = max(e, f[Pt.PEER_ENERGY * n + j])
        i[Pt.CODEC_RX_SEQ] = rx_i[Pk.SEQ]
        i[Pt.CODEC_AGE] = 0
        if wave and i[Pt.RECONSTRUCTION] == REFLECTED and i[Pt.LAST_SEQ] >= 0:
            # the held ticks were the codec's, not losses: no integral to catch up in one
            # tick (a jolt of several ticks' worth of the hold's error, beyond what the TO can
            # follow when packets come late); what the hold missed is the port's debt, paid
            # back at its drift rate. On time a packet is the next in line: unchanged.
            rx_i[Pk.SEQ] = min(rx_i[Pk.SEQ], i[Pt.LAST_SEQ] + 1)
        return
    age = i[Pt.CODEC_AGE] + 1
    i[Pt.CODEC_AGE] = age
    if i[Pt.LAST_SEQ] < 0:
        return  # nothing received yet: nothing to hold
    if age >= i[Pt.CODEC_MAX]:
        i[Pt.CODEC_EXPIRED] += 1  # the peer would have sent by now: a loss
        return
    i[Pt.CODEC_HELD] += 1
    for j in range(n):
        held = _predicted(f[Pt.CODEC_RX * n + j], f[Pt.CODEC_RX_SLOPE * n + j], age)
        if not wave and rate > 0.0:
            debt = f[Pt.CODEC_DEBT * n + j]
            pay = rate * debt * dt
            held += pay / dt
            f[Pt.CODEC_DEBT * n + j] = debt - pay
            f[Pt.CODEC_RX_SUM * n + j] += held * dt
        rx[sig * n + j] = held
        rx[Pk.E_IN * n + j] = f[Pt.PEER_E_IN * n + j]
        rx[Pk.X_SUM * n + j] = f[Pt.PEER_X_SUM * n + j] + held * dt  # as reconstructed
        # what the peer declared in the packets that have arrived (the look-ahead included),
        # not a joule more: the bound holds the wave within it
        rx[Pk.WAVE_ENERGY * n + j] = max(f[Pt.PEER_ENERGY * n + j], f[Pt.CODEC_AHEAD * n + j])
        rx[Pk.WAVE_SUM * n + j] = f[Pt.USED_SUM * n + j] + held * dt  # the integral as used
    rx_i[Pk.SEQ] = i[Pt.LAST_SEQ] + 1  # the next in line: nothing missed, nothing to catch up
    rx_i[Pk.TICK] = rx_i[Pk.SEQ]
    rx_i[Pk.VALID] = 1


@jit
def codec_line_ahead(
    f: np.ndarray, i: np.ndarray, at: np.ndarray, n: int, sender: int, port: np.ndarray,
    port_i: np.ndarray,
) -> None:  # fmt: skip
    """Before the receiving port (``port``): the look-ahead of its room from the in-process
    link's line of packets from ``sender`` (``teleop_rt.com.link``; ``at``: its offsets), which
    stands for a network of no latency and a playout delay of D: every packet in it has
    arrived. The wave energy declared by the newest one sent that is not due this tick (the
    slots pushed 1 .. D - 1 ticks ago; the due one the port credits itself)."""
    Pt, Pk, Ln = Port.idx, Packet.idx, InProcessLink.idx
    if port_i[Pt.CODEC] == NONE or port_i[Pt.MODE] != WAVE:
        return
    d = i[at[LI] + Ln.DELAY_TICKS]
    e, m = entry_size(n), packet_floats(n)
    base, slot = at[LF] + sender * d * e, i[at[LI] + Ln.SLOT]
    for back in range(1, d):
        s = base + ((slot - back) % d) * e
        if f[s + m + Pk.VALID] != 0.0:  # (unsent: a zero entry)
            for j in range(n):
                port[Pt.CODEC_AHEAD * n + j] = f[s + Pk.WAVE_ENERGY * n + j]
            return
    for j in range(n):
        port[Pt.CODEC_AHEAD * n + j] = 0.0


@jit
def codec_send(f: np.ndarray, i: np.ndarray, n: int, tx: np.ndarray, tx_i: np.ndarray) -> None:
    """After the port: send this tick's packet, or mark it unsent (the links carry
    nothing), by the deadband, the intervals and, on a wave channel, the peer's predicted
    energy room."""
    Pt, Pk = Port.idx, Packet.idx
    if i[Pt.CODEC] == NONE or i[Pt.DELAY_TICKS] == 0:
        return
    s = Pt.N_VECTORS * n
    wave = i[Pt.MODE] == WAVE
    sig = Pk.WAVE if wave else Pk.X
    dt = f[s + Pt.DT]
    half_dt = 0.5 * dt
    weber, floor, gain = f[s + Pt.CODEC_WEBER], f[s + Pt.CODEC_FLOOR], f[s + Pt.CODEC_VELOCITY_GAIN]
    reserve, room_ticks = f[s + Pt.CODEC_RESERVE], f[s + Pt.CODEC_ROOM_TICKS]
    step = f[s + Pt.CODEC_ENERGY_STEP]
    exchange = f[s + Pt.CODEC_EXCHANGE_STEP]
    exchange_weber, alpha = f[s + Pt.CODEC_EXCHANGE_WEBER], f[s + Pt.CODEC_FLOW_ALPHA]
    exchange_min = i[Pt.CODEC_EXCHANGE_MIN]
    # with a look-ahead of A ticks the peer's room at its playout of this tick includes the
    # energy declared by any packet sent in the next A ticks: this tick's true wave energy,
    # if one goes out within A + 1 ticks of the last
    ahead = wave and i[Pt.CODEC_AHEAD_TICKS] > 0
    # ``reflected``: the peer's room is no bound to model (it reflects what it holds)
    reflects = wave and i[Pt.RECONSTRUCTION] == REFLECTED
    since = i[Pt.CODEC_SINCE] + 1
    crossed = short = False
    for j in range(n):
        ref = _predicted(f[Pt.CODEC_REF * n + j], f[Pt.CODEC_SLOPE * n + j], since)
        x = tx[sig * n + j]
        k = weber * (1.0 + gain * abs(f[Pt.FLOW * n + j]))
        if abs(x - ref) > k * abs(ref) + floor:
            crossed = True
        if not wave and step > 0.0 and tx[Pk.E_IN * n + j] - f[Pt.CODEC_E_SENT * n + j] > step:
            short = True  # the peer's controller would dissipate what it has not been told
        if not wave and exchange > 0.0:
            # energy crossing the port either way: the contact the peer's hold lags (docs/codec.md)
            crossed_j = tx[Pk.E_IN * n + j] + tx[Pk.E_OUT * n + j]
            # Weber's rule on the energy step: it grows with the NET energy flowing through
            # the port over the last window (the low-passed E_in - E_out per tick, over alpha),
            # so that a steady flow one way (foam's damping) sends a packet per fraction of a
            # window; an oscillation's energy goes back and forth, nets ~0 and keeps the step
            net = tx[Pk.E_IN * n + j] - tx[Pk.E_OUT * n + j]
            flow = f[Pt.CODEC_FLOW * n + j]
            flow += alpha * (net - f[Pt.CODEC_CROSSED_LAST * n + j] - flow)
            f[Pt.CODEC_FLOW * n + j] = flow
            f[Pt.CODEC_CROSSED_LAST * n + j] = net
            grown = exchange + exchange_weber * abs(flow) / alpha
            if crossed_j - f[Pt.CODEC_E_CROSSED * n + j] > grown and since >= exchange_min:
                short = True
        if wave and not reflects:
            # would the peer's bound cut the held wave this tick (the room declared so far)?
            if ahead:
                f[Pt.CODEC_SIM_DECLARED * n + j] = tx[Pk.WAVE_ENERGY * n + j]
            sim_used = f[Pt.CODEC_SIM_USED * n + j] + ref * ref * half_dt
            if sim_used > f[Pt.CODEC_SIM_DECLARED * n + j]:
                short = True
    first = i[Pt.CODEC_SENT] == 0
    due = since >= i[Pt.CODEC_MAX] or (ahead and since > i[Pt.CODEC_AHEAD_TICKS])
    # the clutch or presence changed: the peer decouples on it, so it goes out now
    changed = tx_i[Pk.ENGAGED] != i[Pt.CODEC_ENGAGED]
    crossed = crossed or changed
    if first or due or changed or (since >= i[Pt.CODEC_MIN] and (crossed or short)):
        if crossed or first:
            i[Pt.CODEC_BY_THRESHOLD] += 1
        elif short:
            i[Pt.CODEC_BY_ENERGY] += 1
        else:
            i[Pt.CODEC_BY_INTERVAL] += 1
        i[Pt.CODEC_SENT] += 1
        i[Pt.CODEC_ENGAGED] = tx_i[Pk.ENGAGED]
        tx_i[Pk.UNSENT] = 0
        since_sent, since = since, 0
        for j in range(n):
            x = tx[sig * n + j]
            w = x
            if wave:
                declared = tx[Pk.WAVE_ENERGY * n + j]
                used = f[Pt.CODEC_SIM_USED * n + j]
                # short of the room to hold it a while: send it a little smaller (within the
                # band), so that holding it builds the room (0: off)
                if declared - used - w * w * half_dt < room_ticks * w * w * half_dt:
                    w *= 1.0 - reserve * weber
                tx[sig * n + j] = w
                f[Pt.CODEC_SIM_DECLARED * n + j] = declared
                _peer_uses(f, n, j, w, half_dt, ahead)
            slope = 0.0
            if not first:
                slope = f[s + Pt.CODEC_PREDICT] * (w - f[Pt.CODEC_REF * n + j]) / since_sent
            f[Pt.CODEC_SLOPE * n + j] = slope
            f[Pt.CODEC_REF * n + j] = w
            f[Pt.CODEC_E_SENT * n + j] = tx[Pk.E_IN * n + j]
            f[Pt.CODEC_E_CROSSED * n + j] = tx[Pk.E_IN * n + j] + tx[Pk.E_OUT * n + j]
    else:
        tx_i[Pk.UNSENT] = 1
        i[Pt.CODEC_SILENT] += 1
        if wave:  # the peer holds (or extrapolates) the last wave sent, cut to its room
            for j in range(n):
                w = _predicted(f[Pt.CODEC_REF * n + j], f[Pt.CODEC_SLOPE * n + j], since)
                _peer_uses(f, n, j, w, half_dt, ahead)
    i[Pt.CODEC_SINCE] = since


@jit
def _peer_uses(f: np.ndarray, n: int, j: int, w: float, half_dt: float, ahead: bool) -> None:
    """The peer uses wave ``w`` on joint j this tick, cut by its bound to the room declared:
    the wave energy it has used, as this sender predicts it. With a look-ahead the peer's
    room may be more than this sender knows of yet: uncut (what the peer uses at most)."""
    Pt = Port.idx
    used, e = f[Pt.CODEC_SIM_USED * n + j], w * w * half_dt
    if not ahead:
        e = min(e, max(f[Pt.CODEC_SIM_DECLARED * n + j] - used, 0.0))
    f[Pt.CODEC_SIM_USED * n + j] = used + e


@jit
def _predicted(value: float, slope: float, age: int) -> float:
    """The last packet's value extrapolated ``age`` ticks along its slope (0: held)."""
    return value + slope * age
