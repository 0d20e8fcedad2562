"""The operator's clutch and presence (dead-man) inputs as digital inputs of a CiA 402 drive
(0x60FD, mapped in TPDO3 every SYNC) on the emulated HSI bus: the mapping reads them from the
feedback each tick, with the scripted inputs' ramp and timeout (teleop_rt.mapping)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.errors import ConfigError
from teleop_rt.session import Session

ROOT = Path(__file__).resolve().parents[1]
CAN = ROOT / "configs" / "can_emulated.yaml"
FAST = [
    "can.emulate=true",
    "can.hsi.torque_sensor.zero_ticks=50",
    "can.to.torque_sensor.zero_ticks=50",
]
CLUTCH_NODE, CLUTCH_BIT = 2, 16  # a manufacturer-specific input of the HSI's second drive
CLUTCH = f"can.hsi.clutch_input={{drive: {CLUTCH_NODE}, bit: {CLUTCH_BIT}}}"
PRESENCE = "can.hsi.presence_input={drive: 1, bit: 17}"
# pressed from the observer after tick 5500 (the HSI in the foam, 50 ms of delay: a channel
# torque to take up) to after tick 6499; the drive samples at the next SYNC
PRESSED = range(5500, 6500)
WINDOW = 400  # ticks after the re-engage that count as its transient
ENGAGE_STEP_NM = 0.005  # mapping.engage_step_nm's default
TAU_STEP_BOUND_NM = 2 * ENGAGE_STEP_NM  # the rendered torque's ramp plus the hand's own motion


def session_for(*overrides: str) -> Session:
    return Session(config.load(CAN, [*FAST, "duration_s=8", "channel.delay_ms=50", *overrides]))


def run(session: Session, inputs) -> tuple[np.ndarray, object]:
    """Each tick: ``inputs(tick)`` -> {node: 0x60FD bits} onto the HSI's emulated drives (for
    the next SYNC); rows of rendered torque r tau_c (2), q_h (2), q_t (2), r, the TO's r and
    the wave energy in flight on the link, J."""
    rows: list[np.ndarray] = []

    def observe(s: Session) -> None:
        emu = s.hsi.backend.emulator
        for node, bits in inputs(s.tick).items():
            emu.by_node[node].digital_inputs = bits
        hsi = s.hsi
        rendered = hsi.signals.tau - hsi.signals.error
        energy = s.channel.stored_energy()
        rows.append(np.concatenate([
            rendered, hsi.feedback.q, s.to.feedback.q, [hsi.mapping.gain, s.to.mapping.gain,
                                                        energy]
        ]))  # fmt: skip

    summary = session.run(observer=observe)
    return np.array(rows), summary


def clutch_pressed(node: int = CLUTCH_NODE, bit: int = CLUTCH_BIT):
    return lambda tick: {node: (1 << bit) if tick in PRESSED else 0}


def test_the_clutch_bit_decouples_and_re_engages_within_the_bound() -> None:
    """Bit 16 of drive 2's 0x60FD pressed for 1 s: from the next tick the HSI renders nothing
    and moves on with the hand (> 0.04 rad) while the TO holds (< 1/20 of the HSI's motion);
    released, the coupling comes back with no step in tau_h above the bound and the channel
    made no energy; TPDO3 carries
    0x60FD on the input's drive only."""
    session = session_for(CLUTCH)
    rows, summary = run(session, clutch_pressed())
    assert summary.stopped_early is None and session.hsi.mapping.engagements == 1
    gain = rows[:, 6]
    decoupled = np.flatnonzero(gain == 0)
    assert (decoupled[0], decoupled[-1], len(decoupled)) == (5501, 6500, 1000)
    held = slice(5501, 6501)
    assert np.abs(rows[held, :2]).max() == 0.0  # the HSI free: no channel torque rendered
    hsi_moved, to_moved = np.ptp(rows[held, 2:4], axis=0), np.ptp(rows[held, 4:6], axis=0)
    assert hsi_moved.max() > 0.04 and to_moved.max() < hsi_moved.max() / 20, to_moved
    step = np.abs(np.diff(rows[:, :2], axis=0)).max(axis=1)
    after = step[6500 : 6500 + WINDOW]
    assert 0 < after.max() <= TAU_STEP_BOUND_NM, after.max()
    assert summary.min_channel_energy_j >= -1e-9  # the channel made no energy (measured: 0.0)
    drives = session.hsi.backend.emulator.by_node
    assert tpdo3_maps_0x60fd(drives[CLUTCH_NODE]) and not tpdo3_maps_0x60fd(drives[1])


def tpdo3_maps_0x60fd(drive) -> bool:
    """The start-up wrote 0x60FD:00, 32 bits, as TPDO3's first mapped object (0x1A02:01)."""
    return (0x1A02, 1, 0x60FD0020) in drive.sdo_writes


def test_without_the_ramp_the_same_release_steps_tau_h() -> None:
    """The bound above is the ramp's doing: re-engaging at once steps tau_h beyond it."""
    rows, _ = run(session_for(CLUTCH, "mapping.engage_ramp_s=0", "mapping.engage_step_nm=1e9"),
                  clutch_pressed())  # fmt: skip
    step = np.abs(np.diff(rows[:, :2], axis=0)).max(axis=1)
    assert step[6500 : 6500 + WINDOW].max() > TAU_STEP_BOUND_NM


@pytest.mark.parametrize("node, bit", [(CLUTCH_NODE, CLUTCH_BIT + 1), (1, CLUTCH_BIT)])
def test_another_bit_or_drive_is_not_the_clutch(node: int, bit: int) -> None:
    rows, summary = run(session_for(CLUTCH, "duration_s=7"), clutch_pressed(node, bit))
    assert summary.stopped_early is None and (rows[:, 6] == 1.0).all()


def present(away: range):
    return lambda tick: {1: 0 if tick in away else 1 << 17}


def test_presence_lost_briefly_decouples_and_too_long_is_a_safe_stop() -> None:
    """The dead-man on drive 1's bit 17, timeout 0.5 s: 0.4 s away decouples for exactly
    those ticks and re-engages; 1 s away stops the session once 0.5 s have passed. (Until
    the observer's first tick the bit is off: tick 0 counts as away.)"""
    timeout = "mapping.presence_timeout_s=0.5"
    session = session_for(PRESENCE, timeout, "duration_s=3")
    rows, summary = run(session, present(range(1000, 1400)))
    gain = rows[:, 6]
    assert summary.stopped_early is None and session.hsi.mapping.engagements == 2
    assert (gain[1001:1401] == 0).all() and gain[1401] > 0 and gain[1000] > 0
    assert np.abs(rows[1001:1401, :2]).max() == 0.0
    stopped = session_for(PRESENCE, timeout, "duration_s=3")
    _, summary = run(stopped, present(range(1000, 2000)))
    assert summary.safety_stop and "away for more than 0.5 s" in (summary.stopped_early or "")
    assert summary.ticks == 1501  # away from tick 1001: at tick 1501 for 501 ticks, a stop


@pytest.mark.parametrize("override, message", [
    ("can.hsi.clutch_input={drive: 1, bit: 32}",
     "can.hsi.clutch_input.bit: Input should be less than or equal to 31"),
    ("can.hsi.presence_input={drive: 9, bit: 3}",
     "can.hsi: presence_input.drive: node 9 is not one of this bus's drives [1, 2]"),
    ("can.to.clutch_input={drive: 1, bit: 3}",
     "can: to.clutch_input: the operator's clutch and presence are the HSI's"),
])  # fmt: skip
def test_a_bad_input_is_one_clear_line(override: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        config.load(CAN, [override])
    assert str(err.value) == message


def test_without_the_keys_no_tpdo3_and_the_mapping_stays_the_identity() -> None:
    session = Session(config.load(CAN, [*FAST, "duration_s=0.1"]))
    session.run()
    assert session.hsi.mapping.active == 0 and session.hsi.mapping.live == 0
    assert not any(map(tpdo3_maps_0x60fd, session.hsi.backend.emulator.drives))


DELAY_TICKS = 50  # channel.delay_ms=50 at 1 kHz


def test_the_to_decouples_on_the_hsis_packets_and_drains_the_channel() -> None:
    """The HSI's coupling state rides in its packets (``Packet.engaged``): the TO decouples
    D + 1 ticks after the HSI (the packet of the HSI's first decoupled tick reaches the TO
    after D, and is read by its next tick's map) and its port is terminated, a matched damper
    that absorbs the waves left in the channel while the HSI, at zero flow, reflects them: in
    closed form the lines are empty 2 D + 1 ticks after the TO decoupled (0 J), but for what
    the received-wave filters (30 Hz here) still let out, which decays geometrically from
    then on (measured at release: 1.3e-143 J; the TO coupled to the reflecting HSI kept
    ~0.0028 J). On release the TO re-engages D + 1 ticks after the HSI, with the same
    ramp."""
    session = session_for(CLUTCH)
    rows, summary = run(session, clutch_pressed())
    assert summary.stopped_early is None
    hsi_gain, to_gain, energy = rows[:, 6], rows[:, 7], rows[:, 8]
    hsi_off, to_off = np.flatnonzero(hsi_gain == 0), np.flatnonzero(to_gain == 0)
    assert to_off[0] - hsi_off[0] == DELAY_TICKS + 1, (hsi_off[0], to_off[0])
    assert to_off[-1] - hsi_off[-1] == DELAY_TICKS + 1 and len(to_off) == len(hsi_off)
    release = hsi_off[-1]  # the HSI's last decoupled tick
    assert energy[hsi_off[0]] > 1e-3  # (there was a wave to drain)
    assert energy[release] <= 1e-9, energy[release]
    assert (np.diff(energy[to_off[0] + 2 * DELAY_TICKS + 1 : release + 1]) <= 0).all()
    assert session.to.mapping.engagements == 1
    rise = np.diff(to_gain[to_off[-1] :])
    step = session.to.mapping.ramp_step  # the TO's gain climbs by the ramp, no faster
    assert rise.max() <= step * (1 + 1e-12) and 0 < to_gain[to_off[-1] + 1] < 1
    assert summary.min_channel_energy_j >= -1e-9
