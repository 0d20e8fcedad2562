"""Honest energy credit (issue 23): the bounded wave reconstruction spends only the energy of
waves that reached its port in time. Proven on one port alone, driven by a scripted packet
sequence of a peer whose waves, wave integral and cumulative wave energy are computed here as
the peer's port computes them.

The measured ratchet this guards against: a packet arriving after a long outage carries the
peer's cumulative wave energy including the samples never delivered; credited, that energy
stayed in the balance, and in the next outage the stale held wave was emitted until it was
spent (it behaved like ``hold``: the robots drifted into a joint limit).
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.channel import make_port
from teleop_rt.com.port import CATCH_UP, HOLD_TICKS, TO, Packet, port_input, port_step

DT = 1e-3
PASSIVE_J = -1e-9


def drive(
    waves: np.ndarray, arrives: np.ndarray, filter_hz: float | None = None
) -> dict[str, np.ndarray]:
    """The TO's port (b = 2, tau_t = 0; ``filter_hz``: the received-wave filter) fed the peer's
    packet k at tick k when ``arrives[k]``, else none; per tick the wave it used (what the
    filter gave the port), its honest balance, the wave energy it has used and emitted, and
    its budget at the end."""
    port = make_port(TO, "wave", [2.0], 5, DT, filter_hz, "bounded")
    rx, tx = Packet(1), Packet(1)
    used, balance, energy, emitted = (np.zeros(waves.size) for _ in range(4))
    wave_sum = wave_energy = 0.0
    for k, w in enumerate(waves):
        wave_sum += w * DT
        wave_energy += w * w * 0.5 * DT
        port_input(port.f, port.i, 1, np.zeros(1), tx.f)
        rx.f[:], rx.i[:] = 0.0, 0
        if arrives[k]:
            rx.wave[0], rx.wave_sum[0], rx.wave_energy[0] = w, wave_sum, wave_energy
            rx.tick = rx.seq = k
            rx.valid = 1
        port_step(port.f, port.i, 1, rx.f, rx.i, tx.f)
        used[k], balance[k], energy[k] = port.wave_in[0], port.balance, port.used_energy[0]
        emitted[k] = port.out_energy[0]
    return {"used": used, "balance": balance, "energy": energy, "emitted": emitted,
            "got": port.got_energy[0]}  # fmt: skip


def test_a_packet_after_a_long_outage_brings_no_credit_for_a_stale_wave() -> None:
    """A steady wave, an outage of 500 ticks, 100 packets, a second outage: after the first
    outage's packet the port has no credit beyond what it received, so in the second outage
    it emits nothing (old credit: the held wave for all 500 ticks)."""
    ticks, w0 = 1300, 0.5
    arrives = np.ones(ticks, bool)
    arrives[200:700] = arrives[800:] = False
    out = drive(np.full(ticks, w0), arrives)
    assert out["balance"].min() >= PASSIVE_J
    # the burst of arrivals after the long gap: taken as it is, nothing caught up
    assert np.all(out["used"][700:800] == w0)
    e0 = w0 * w0 * 0.5 * DT
    assert out["balance"][799] <= e0 * 1e-9  # no credit carried into the second outage
    second = out["used"][800:]
    assert np.count_nonzero(second) <= HOLD_TICKS
    assert out["energy"][-1] - out["energy"][799] <= out["balance"][799] + 1e-18


def test_a_held_wave_expires_and_its_credit_with_it() -> None:
    """Credit a port may keep (a catch-up whose samples cancel spends less than this sample's
    energy) is spent by a held wave for at most HOLD_TICKS ticks of an outage, then given up:
    here 100 catch-ups bank ~100 samples' energy before a 500-tick outage, in which the held
    (small) wave could otherwise go on for all of it."""
    ticks, a, eps = 900, 0.4, 1e-3
    # per 4 ticks: eps, eps, -a (lost), +a (its catch-up sums to a zero wave)
    waves = np.tile([eps, eps, -a, a], ticks // 4)
    arrives = np.ones(ticks, bool)
    arrives[2:400:4] = False
    arrives[398:] = False  # the outage: the last sample used is an eps
    out = drive(waves, arrives)
    assert out["balance"].min() >= PASSIVE_J
    banked = out["balance"][397]
    catch_ups = np.count_nonzero(~arrives[:398])
    # each banks at most its own sample's energy (not the skipped one's), and does bank it
    assert 0.9 * catch_ups * a * a * 0.5 * DT < banked <= (1 + 1e-9) * catch_ups * a * a * 0.5 * DT
    held = np.flatnonzero(out["used"][398:])
    assert held.size == HOLD_TICKS and held.max() == HOLD_TICKS - 1
    assert np.all(out["used"][398 : 398 + HOLD_TICKS] == eps)
    assert out["balance"][-1] == 0.0  # given up when the hold expired


def test_a_catch_up_spends_only_the_energy_of_the_samples_it_catches_up() -> None:
    """A gap of 5 packets (within CATCH_UP) in a steady wave: the catch-up tick may spend the
    6 samples' energy, no more; what it does not spend of them is not kept."""
    ticks, w0 = 60, 0.3
    assert 5 <= CATCH_UP
    arrives = np.ones(ticks, bool)
    arrives[20:25] = False
    out = drive(np.full(ticks, w0), arrives)
    e0 = w0 * w0 * 0.5 * DT
    assert np.all(out["used"][20:25] == 0.0)  # no credit for the held wave
    # the catch-up's sum of 6 samples is cut to their energy: sqrt(6) w0, not 6 w0
    assert np.isclose(out["used"][25], np.sqrt(6.0) * w0, rtol=1e-12)
    assert abs(out["balance"][25]) <= 1e-12 * e0
    assert np.all(out["used"][26:] == w0) and out["balance"].min() >= PASSIVE_J



def test_a_standing_wave_is_held_through_a_short_burst_on_the_filters_unspent_energy() -> None:
    """A steady wave (a static push) and a burst of 6 lost packets: the filter's lag left
    about 1.5 / alpha samples' energy unspent, so the held wave keeps the port's wave where
    it was (a zero wave lets it decay by (1 - alpha) per tick); the catch-up's skipped samples
    pay it back. What the filter gives the port never exceeds what reached it in time."""
    ticks, w0 = 400, 0.5
    arrives = np.ones(ticks, bool)
    arrives[300:306] = False
    out = drive(np.full(ticks, w0), arrives, filter_hz=30.0)
    assert out["balance"].min() >= PASSIVE_J
    got = np.cumsum(np.where(arrives, w0 * w0 * 0.5 * DT, 0.0))
    assert np.all(out["emitted"] <= got + 1e-15)  # emitted <= received in time, every tick
    assert np.all(np.abs(out["used"][300:306] - w0) < 1e-6 * w0)  # held, not decayed
    assert np.abs(out["used"][306:] - w0).max() < 0.05 * w0
