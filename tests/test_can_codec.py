"""Tests for the bus-free CANopen codec (teleop_rt.hal.can.codec) and the CiA 402 stepper.

Expected values are worked by hand from CiA 301 / CiA 402 and the closed-form unit conversions;
the only canopen table the tests reuse is the one the fake drive needs (TRANSITIONTABLE).
"""

import math
import os
import subprocess
import sys
from collections import deque
from pathlib import Path

import pytest
from canopen.profiles.p402 import State402
from hypothesis import given
from hypothesis import strategies as st

from teleop_rt.errors import BackendError
from teleop_rt.hal.can import cia402, codec
from teleop_rt.hal.can.cia402 import Cia402Stepper, decode_statusword
from teleop_rt.hal.can.codec import CanFrameError, JointUnits

INT16 = st.integers(-(2**15), 2**15 - 1)
UINT16 = st.integers(0, 2**16 - 1)
INT32 = st.integers(-(2**31), 2**31 - 1)


# --- COB-IDs -------------------------------------------------------------------------------
def test_cob_ids_follow_the_predefined_connection_set() -> None:
    assert codec.COB_ID_SYNC == 0x080
    assert codec.emcy_cob_id(1) == 0x081
    assert codec.tpdo1_cob_id(5) == 0x185
    assert codec.rpdo1_cob_id(5) == 0x205
    assert codec.tpdo2_cob_id(5) == 0x285
    assert codec.heartbeat_cob_id(127) == 0x77F


@pytest.mark.parametrize("bad", [0, 128, -1, 1.0, True, "5", None])
def test_node_id_outside_1_to_127_is_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match=r"node id must be an integer in 1\.\.127"):
        codec.rpdo1_cob_id(bad)  # type: ignore[arg-type]


# --- PDO round trips and byte layouts ------------------------------------------------------
@given(UINT16, INT16)
def test_rpdo1_round_trip(controlword: int, torque: int) -> None:
    buf = bytearray(4)
    codec.pack_rpdo1(buf, controlword, torque)
    assert codec.unpack_rpdo1(buf) == (controlword, torque)


@given(INT32, INT32)
def test_tpdo1_round_trip(counts: int, velocity: int) -> None:
    buf = bytearray(8)
    codec.pack_tpdo1(buf, counts, velocity)
    assert codec.unpack_tpdo1(bytes(buf)) == (counts, velocity)


@given(UINT16, INT16)
def test_tpdo2_round_trip(statusword: int, torque: int) -> None:
    buf = bytearray(4)
    codec.pack_tpdo2(buf, statusword, torque)
    assert codec.unpack_tpdo2(memoryview(buf)) == (statusword, torque)


def test_pdo_byte_layouts_are_little_endian() -> None:
    buf = bytearray(4)
    codec.pack_rpdo1(buf, 0x000F, -500)  # -500 = 0xFE0C
    assert buf == b"\x0f\x00\x0c\xfe"
    # 102400 = 0x00019000, -1 = 0xFFFFFFFF
    assert codec.unpack_tpdo1(b"\x00\x90\x01\x00\xff\xff\xff\xff") == (102400, -1)
    # statusword 0x0237 (operation enabled), torque actual 1000 = 0x03E8
    assert codec.unpack_tpdo2(b"\x37\x02\xe8\x03") == (0x0237, 1000)


def test_pack_writes_into_the_callers_buffer() -> None:
    buf = bytearray(4)
    before = id(buf)
    codec.pack_rpdo1(buf, 0x06, 0)
    assert id(buf) == before and buf == b"\x06\x00\x00\x00"


@pytest.mark.parametrize(
    ("controlword", "torque"), [(0x10000, 0), (-1, 0), (0x0F, 2**15), (0x0F, 1.0)]
)
def test_pack_rpdo1_rejects_out_of_range_values(controlword: object, torque: object) -> None:
    with pytest.raises(ValueError, match="RPDO1"):
        codec.pack_rpdo1(bytearray(4), controlword, torque)  # type: ignore[arg-type]


@pytest.mark.parametrize("size", [3, 5, 8])
def test_pack_rpdo1_rejects_a_buffer_of_the_wrong_size(size: int) -> None:
    with pytest.raises(ValueError, match=rf"RPDO1.*buffer must be 4 bytes, got {size}"):
        codec.pack_rpdo1(bytearray(size), 0, 0)


# --- wrong-length frames -------------------------------------------------------------------
# a shorter PDO is an error, a longer one is read (CiA 301); EMCY and heartbeat have one length
@pytest.mark.parametrize(
    ("decode", "obj", "expected", "delta"),
    [
        (codec.unpack_rpdo1, "RPDO1", 4, -1),
        (codec.unpack_tpdo1, "TPDO1", 8, -1),
        (codec.unpack_tpdo2, "TPDO2", 4, -1),
        (codec.decode_emcy, "EMCY", 8, -1),
        (codec.decode_emcy, "EMCY", 8, +1),
        (codec.decode_heartbeat, "heartbeat", 1, -1),
        (codec.decode_heartbeat, "heartbeat", 1, +1),
    ],
)
def test_wrong_length_frame_names_object_and_lengths(decode, obj, expected, delta) -> None:
    received = expected + delta
    with pytest.raises(ValueError) as info:
        decode(bytes(received))
    message = str(info.value)
    assert obj in message
    assert f"expected {expected} data bytes, received {received}" in message
    assert "\n" not in message
    # One error tree: the CLI prints a BackendError as one line.
    assert isinstance(info.value, CanFrameError) and isinstance(info.value, BackendError)


@pytest.mark.parametrize(
    ("decode", "size"),
    [(codec.unpack_rpdo1, 4), (codec.unpack_tpdo1, 8), (codec.unpack_tpdo2, 4)],
)
def test_a_longer_pdo_is_read_from_its_leading_bytes(decode, size) -> None:
    """CiA 301: a PDO consumer uses the mapped leading bytes of a longer PDO."""
    frame = bytes(range(1, size + 1))
    assert decode(frame + b"\xff\xee") == decode(frame)
    assert codec.pdo_excess("x", size, frame + b"\xff") == 1
    assert codec.pdo_excess("x", size, frame) == 0


def test_tpdo1_length_error_names_the_mapped_objects() -> None:
    with pytest.raises(ValueError, match=r"0x6064.*0x606C.*expected 8 data bytes, received 7"):
        codec.unpack_tpdo1(bytes(7))


# --- EMCY and heartbeat on literal frames --------------------------------------------------
def test_emcy_decodes_code_register_and_manufacturer_bytes() -> None:
    # 0x8210 "PDO not processed due to length error", error register 0x11 (generic + comms)
    emcy = codec.decode_emcy(b"\x10\x82\x11\x01\x02\x03\x04\x05")
    assert emcy == codec.Emcy(0x8210, 0x11, b"\x01\x02\x03\x04\x05")
    assert emcy.error_code == 0x8210 and emcy.error_register == 0x11
    assert not emcy.is_reset
    assert emcy.describe() == (
        "EMCY 0x8210 (Monitoring), error register 0x11, manufacturer data 01 02 03 04 05"
    )


def test_emcy_error_reset() -> None:
    emcy = codec.decode_emcy(bytes(8))
    assert emcy == (0, 0, bytes(5)) and emcy.is_reset


@pytest.mark.parametrize(
    ("frame", "name"),
    [
        (b"\x00", "BOOT-UP"),
        (b"\x04", "STOPPED"),
        (b"\x05", "OPERATIONAL"),
        (b"\x7f", "PRE-OPERATIONAL"),
        (b"\x85", "OPERATIONAL"),  # node-guarding reply with the toggle bit set
    ],
)
def test_heartbeat_states(frame: bytes, name: str) -> None:
    assert codec.decode_heartbeat(frame) == name


def test_heartbeat_unknown_state_is_one_clear_line() -> None:
    message = r"^heartbeat \(NMT state u8\): unknown NMT state 0x02$"
    with pytest.raises(CanFrameError, match=message):
        codec.decode_heartbeat(b"\x02")


@pytest.mark.parametrize(
    ("error_id", "data", "text"),
    [
        (0x040, bytes(8), "CAN error frame 0x040 (bus off)"),
        (0x020, bytes(8), "CAN error frame 0x020 (no ACK on transmission)"),
        (
            0x004,
            b"\x00\x30" + bytes(6),
            "CAN error frame 0x004 (controller problem: RX error passive, TX error passive)",
        ),
        (
            0x044,
            b"\x00\x01",
            "CAN error frame 0x044 (bus off; controller problem: RX buffer overflow)",
        ),
        (0x004, b"", "CAN error frame 0x004 (controller problem)"),  # no detail byte
        (0x000, bytes(8), "CAN error frame 0x000"),  # another interface's code: the number only
    ],
)
def test_error_frames_are_described_by_socketcan_class(error_id: int, data: bytes, text: str):
    assert codec.describe_error_frame(error_id, data) == text


@pytest.mark.parametrize(
    ("error_id", "data", "fault"),
    [
        (0x002, bytes(8), False),  # lost arbitration: the controller sends the frame again
        (0x200, bytes(8), False),  # error counters only
        (0x004, b"\x00\x04" + bytes(6), False),  # RX error warning
        (0x004, b"\x00\x48" + bytes(6), False),  # TX error warning, back to error active
        (0x206, b"\x00\x08" + bytes(6), False),  # all three warnings in one frame
        (0x004, b"\x00\x10" + bytes(6), True),  # RX error passive
        (0x004, b"\x00\x05" + bytes(6), True),  # a warning with an RX overflow
        (0x004, b"\x00\x00" + bytes(6), True),  # unspecified controller problem
        (0x004, b"", True),  # no detail byte
        (0x003, bytes(8), True),  # lost arbitration with a TX timeout
        (0x040, bytes(8), True),  # bus off
        (0x020, bytes(8), True),  # no ACK
        (0x000, bytes(8), True),  # another interface's code
    ],
)
def test_only_warning_error_frames_are_not_faults(error_id: int, data: bytes, fault: bool):
    assert codec.error_frame_is_fault(error_id, data) is fault


# --- unit conversions ----------------------------------------------------------------------
# 4096 counts/rev, gear 50: one joint rev = 204800 counts. Rated motor torque 0.1 N m
# (0x6076 = 100 mN m) -> rated joint torque 0.1 * 50 = 5 N m, so 1 per-mille = 5 mN m joint.
UNITS_NEG = JointUnits(4096, 50, 0.1, direction=-1)
UNITS_POS = JointUnits(4096, 50, 0.1, direction=1)


def test_counts_to_rad_worked_example() -> None:
    # 102400 counts = 25 motor revs = 0.5 joint rev, negated by direction -1 -> -pi rad
    assert UNITS_NEG.counts_to_rad(102400) == pytest.approx(-math.pi, rel=1e-15)
    assert UNITS_POS.counts_to_rad(-204800) == pytest.approx(-2 * math.pi, rel=1e-15)
    assert UNITS_POS.counts_to_rad(1) == pytest.approx(2 * math.pi / 204800, rel=1e-15)


def test_velocity_rpm_worked_example() -> None:
    # 3000 motor rpm / 50 = 60 joint rpm = 1 joint rev/s = 2 pi rad/s
    assert UNITS_POS.velocity_to_rad_s(3000) == pytest.approx(2 * math.pi, rel=1e-15)
    assert UNITS_NEG.velocity_to_rad_s(3000) == pytest.approx(-2 * math.pi, rel=1e-15)


def test_velocity_counts_per_s_worked_example() -> None:
    units = JointUnits(4096, 50, 0.1, direction=-1, velocity_unit="counts_per_s")
    # 204800 counts/s = 50 motor rev/s = 1 joint rev/s, negated
    assert units.velocity_to_rad_s(204800) == pytest.approx(-2 * math.pi, rel=1e-15)


def test_torque_to_permille_worked_example() -> None:
    # 2.5 N m joint / 5 N m rated joint = 0.5 -> 500 per-mille, sign by direction
    assert UNITS_POS.torque_nm_to_permille(2.5) == (500, False)
    assert UNITS_NEG.torque_nm_to_permille(2.5) == (-500, False)
    assert UNITS_POS.torque_nm_to_permille(0.0123) == (2, False)  # 2.46 rounds to 2
    assert UNITS_POS.torque_nm_to_permille(-0.0138) == (-3, False)  # -2.76 rounds to -3


def test_permille_to_torque_worked_example() -> None:
    assert UNITS_POS.permille_to_torque_nm(1000) == pytest.approx(5.0, rel=1e-15)
    assert UNITS_POS.permille_to_torque_nm(-250) == pytest.approx(-1.25, rel=1e-15)
    assert UNITS_NEG.permille_to_torque_nm(-250) == pytest.approx(1.25, rel=1e-15)


def test_torque_saturates_to_int16() -> None:
    # int16 max 32767 per-mille = 163.835 N m joint here
    assert UNITS_POS.torque_nm_to_permille(200.0) == (32767, True)
    assert UNITS_POS.torque_nm_to_permille(-200.0) == (-32768, True)
    assert UNITS_NEG.torque_nm_to_permille(200.0) == (-32768, True)
    assert UNITS_POS.torque_nm_to_permille(math.inf) == (32767, True)
    assert UNITS_POS.torque_nm_to_permille(163.8) == (32760, False)
    # Saturated only if rounding alone cannot represent it: 1 N m rated, gear 1 -> 1000 * tau
    unit = JointUnits(1, 1, 1.0)
    assert unit.torque_nm_to_permille(32.767) == (32767, False)  # 32767.000000000004
    assert unit.torque_nm_to_permille(32.7674) == (32767, False)
    assert unit.torque_nm_to_permille(-32.7684) == (-32768, False)
    assert unit.torque_nm_to_permille(32.7676) == (32767, True)
    assert unit.torque_nm_to_permille(-32.7686) == (-32768, True)


def test_torque_nan_is_rejected() -> None:
    with pytest.raises(ValueError, match="NaN"):
        UNITS_POS.torque_nm_to_permille(math.nan)


@given(st.floats(allow_nan=False, allow_infinity=True))
def test_torque_permille_is_int16_and_flags_exactly_the_clamped_requests(tau: float) -> None:
    permille, saturated = UNITS_NEG.torque_nm_to_permille(tau)
    assert isinstance(permille, int) and -(2**15) <= permille <= 2**15 - 1
    ideal = tau * -200.0  # -1000 / (0.1 * 50); both factors are exact in binary
    assert saturated == (ideal >= 2**15 - 0.5 or ideal <= -(2**15) - 0.5)
    if saturated:
        assert permille == (2**15 - 1 if ideal > 0 else -(2**15))
    else:
        assert abs(permille - ideal) <= 0.5


@given(INT16, st.integers(-100000, 100000), st.sampled_from([1, -1]))
def test_joint_power_equals_motor_power(permille: int, rpm: int, direction: int) -> None:
    # Ideal gearbox and one sign for position, velocity and torque: tau_j * w_j = tau_m * w_m
    units = JointUnits(4096, 50, 0.1, direction=direction)
    joint = units.permille_to_torque_nm(permille) * units.velocity_to_rad_s(rpm)
    motor = (permille / 1000.0 * 0.1) * (rpm * 2 * math.pi / 60.0)
    assert joint == pytest.approx(motor, rel=1e-12, abs=1e-12)


def test_rated_torque_from_0x6076() -> None:
    assert codec.rated_torque_nm(100) == pytest.approx(0.1)  # CiA 402: mN m
    assert codec.rated_torque_nm(100_000, unit_nm=1e-6) == pytest.approx(0.1)
    units = JointUnits.from_od(4096, 50, 100, direction=-1)
    assert units == UNITS_NEG
    for bad in (0, -5, 1.5, True, 2**32):
        with pytest.raises(ValueError, match="0x6076"):
            codec.rated_torque_nm(bad)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"counts_per_rev": 0}, "counts_per_rev"),
        ({"gear_ratio": -50}, "gear_ratio"),
        ({"rated_torque_nm": math.nan}, "rated_torque_nm"),
        ({"rated_torque_nm": math.inf}, "rated_torque_nm"),
        ({"direction": 0}, "direction"),
        ({"direction": True}, "direction"),
        ({"velocity_unit": "rad/s"}, "velocity_unit"),
    ],
)
def test_joint_units_validation(kwargs: dict, field: str) -> None:
    args = {"counts_per_rev": 4096, "gear_ratio": 50, "rated_torque_nm": 0.1} | kwargs
    with pytest.raises(ValueError, match=f"JointUnits.{field}"):
        JointUnits(**args)


def test_package_import_is_light() -> None:
    # The package and the codec must not pull in python-can / canopen (cia402 may).
    code = (
        "import sys, teleop_rt.hal.can, teleop_rt.hal.can.codec; "
        "assert 'canopen' not in sys.modules and 'can' not in sys.modules, sys.modules.keys()"
    )
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": root}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=root)


# --- CiA 402 statusword decoding -----------------------------------------------------------
# Statuswords written from the CiA 402 table (bits 6..0), with bit 9 "remote" and bit 4
# "voltage enabled" set where a real drive would, to show that extra bits are ignored.
SW = {
    cia402.NOT_READY_TO_SWITCH_ON: 0x0200,  # x0xx 0000
    cia402.SWITCH_ON_DISABLED: 0x0240,  # x1xx 0000
    cia402.READY_TO_SWITCH_ON: 0x0231,  # x01x 0001
    cia402.SWITCHED_ON: 0x0233,  # x01x 0011
    cia402.OPERATION_ENABLED: 0x0237,  # x01x 0111
    cia402.QUICK_STOP_ACTIVE: 0x0217,  # x00x 0111
    cia402.FAULT_REACTION_ACTIVE: 0x021F,  # x0xx 1111
    cia402.FAULT: 0x0218,  # x0xx 1000
}

# Controlword the stepper must answer with, from the CiA 402 state diagram.
TOWARD_ENABLED = {
    cia402.NOT_READY_TO_SWITCH_ON: 0x00,  # wait for automatic transition 1
    cia402.SWITCH_ON_DISABLED: 0x06,  # shutdown, transition 2
    cia402.READY_TO_SWITCH_ON: 0x07,  # switch on, transition 3
    cia402.SWITCHED_ON: 0x0F,  # enable operation, transition 4
    cia402.OPERATION_ENABLED: 0x0F,  # stay
    cia402.QUICK_STOP_ACTIVE: 0x00,  # disable voltage, transition 12
    cia402.FAULT_REACTION_ACTIVE: 0x00,  # wait for automatic transition 14
    cia402.FAULT: 0x00,  # first tick of a fault: bit 7 low before the rising edge
}


@pytest.mark.parametrize("state", list(SW))
def test_decode_statusword(state: str) -> None:
    assert decode_statusword(SW[state]) == state
    assert decode_statusword(SW[state] & 0x7F) == state  # only the low bits matter


def test_decode_statusword_unknown() -> None:
    assert decode_statusword(0x0048) == cia402.UNKNOWN  # fault bit with switch-on-disabled bit


@pytest.mark.parametrize("state", list(SW))
def test_first_controlword_per_state(state: str) -> None:
    stepper = Cia402Stepper()
    assert stepper.step(SW[state]) == TOWARD_ENABLED[state]
    assert stepper.state == state
    assert stepper.torque_allowed == (state == cia402.OPERATION_ENABLED)


# --- a tiny fake drive ---------------------------------------------------------------------
def _command(cw: int) -> int:
    """Decode a controlword (bit 7 low) to a canopen CW_* command, per CiA 402 command coding."""
    if cw & 0x02 == 0:
        return State402.CW_DISABLE_VOLTAGE  # 0xxx xx0x
    if cw & 0x06 == 0x02:
        return State402.CW_QUICK_STOP  # 0xxx x01x
    if cw & 0x07 == 0x06:
        return State402.CW_SHUTDOWN  # 0xxx x110
    if cw & 0x0F == 0x07:
        return State402.CW_SWITCH_ON  # 0xxx 0111 (also "disable operation")
    return State402.CW_OPERATION_ENABLED  # 0xxx 1111


# Commanded transitions: canopen's TRANSITIONTABLE inverted to (state, command) -> next state.
# Automatic ones (0, 1, 14) and the fault reset (15, an edge, not a level) are modelled apart.
_AUTOMATIC = ("START", cia402.NOT_READY_TO_SWITCH_ON, cia402.FAULT_REACTION_ACTIVE, cia402.FAULT)
NEXT = {(a, cw): b for (a, b), cw in State402.TRANSITIONTABLE.items() if a not in _AUTOMATIC}
# Transitions 7 and 10 also fire on quick stop (CiA 402); canopen lists only disable voltage.
NEXT[(cia402.READY_TO_SWITCH_ON, State402.CW_QUICK_STOP)] = cia402.SWITCH_ON_DISABLED
NEXT[(cia402.SWITCHED_ON, State402.CW_QUICK_STOP)] = cia402.SWITCH_ON_DISABLED


class FakeDrive:
    """CiA 402 device side: one controlword in, one state transition (at most) per tick.

    ``lag`` delays the reported statusword by whole ticks, like a TPDO sampled before the
    RPDO is processed. ``qs_ramp_ticks`` models quick stop option codes 1..4: after that many
    ticks in QUICK STOP ACTIVE the drive goes to SWITCH ON DISABLED by itself (transition 12);
    ``None`` models 5..8 (stay until disable voltage).
    """

    def __init__(self, state: str, lag: int = 0, qs_ramp_ticks: int | None = 3) -> None:
        self.state = state
        self.fault_present = False
        self.resets_seen = 0
        self._prev_cw = 0
        self._qs_ticks = 0
        self._qs_ramp_ticks = qs_ramp_ticks
        self._reported = deque([state] * (lag + 1), maxlen=lag + 1)

    @property
    def statusword(self) -> int:
        return SW[self._reported[0]]

    def inject_fault(self) -> None:
        self.fault_present = True
        self.state = cia402.FAULT_REACTION_ACTIVE  # transition 13, from any state
        self._reported[-1] = self.state  # newest report; a lagged drive shows it later

    def apply(self, cw: int) -> None:
        rising = bool(cw & 0x80 and not self._prev_cw & 0x80)
        self._prev_cw = cw
        s = self.state
        if s == cia402.NOT_READY_TO_SWITCH_ON:
            self.state = cia402.SWITCH_ON_DISABLED  # 1: self-test done
        elif s == cia402.FAULT_REACTION_ACTIVE:
            self.state = cia402.FAULT  # 14: reaction done
        elif s == cia402.FAULT:
            if rising:
                self.resets_seen += 1
                if not self.fault_present:
                    self.state = cia402.SWITCH_ON_DISABLED  # 15
        elif not cw & 0x80:
            cmd = _command(cw)
            if s == cia402.QUICK_STOP_ACTIVE and cmd == State402.CW_QUICK_STOP:
                self._qs_ticks += 1
                if self._qs_ramp_ticks is not None and self._qs_ticks >= self._qs_ramp_ticks:
                    self.state = cia402.SWITCH_ON_DISABLED  # 12: ramp done (option 1..4)
            else:
                self.state = NEXT.get((s, cmd), s)
            if self.state != cia402.QUICK_STOP_ACTIVE:
                self._qs_ticks = 0
        self._reported.append(self.state)


def run(stepper: Cia402Stepper, drive: FakeDrive, ticks: int) -> list[tuple[str, int, bool]]:
    """Tick loop: read statusword -> step -> write controlword. Returns (seen, cw, allowed)."""
    trace = []
    for _ in range(ticks):
        cw = stepper.step(drive.statusword)
        trace.append((stepper.state, cw, stepper.torque_allowed))
        drive.apply(cw)
    return trace


def _never_two_resets_in_a_row(trace: list[tuple[str, int, bool]]) -> bool:
    return all(
        not (a[1] & 0x80 and b[1] & 0x80) for a, b in zip(trace[:-1], trace[1:], strict=True)
    )


def test_power_up_to_operation_enabled() -> None:
    drive = FakeDrive(cia402.NOT_READY_TO_SWITCH_ON)
    trace = run(Cia402Stepper(), drive, 6)
    assert trace == [
        (cia402.NOT_READY_TO_SWITCH_ON, 0x00, False),
        (cia402.SWITCH_ON_DISABLED, 0x06, False),
        (cia402.READY_TO_SWITCH_ON, 0x07, False),
        (cia402.SWITCHED_ON, 0x0F, False),
        (cia402.OPERATION_ENABLED, 0x0F, True),
        (cia402.OPERATION_ENABLED, 0x0F, True),
    ]


@pytest.mark.parametrize("lag", [1, 2, 3])
def test_power_up_with_statusword_lag_converges(lag: int) -> None:
    drive = FakeDrive(cia402.SWITCH_ON_DISABLED, lag=lag)
    trace = run(Cia402Stepper(), drive, 20)
    assert trace[-1] == (cia402.OPERATION_ENABLED, 0x0F, True)
    assert drive.state == cia402.OPERATION_ENABLED


def test_fault_reset_is_a_single_tick_rising_edge() -> None:
    drive = FakeDrive(cia402.OPERATION_ENABLED)
    stepper = Cia402Stepper()
    run(stepper, drive, 2)
    drive.inject_fault()
    drive.fault_present = False  # transient fault: the first reset clears it
    trace = run(stepper, drive, 7)
    assert [cw for _, cw, _ in trace] == [0x00, 0x00, 0x80, 0x06, 0x07, 0x0F, 0x0F]
    assert [s for s, _, _ in trace][:3] == [
        cia402.FAULT_REACTION_ACTIVE,
        cia402.FAULT,
        cia402.FAULT,
    ]
    assert [allowed for _, _, allowed in trace] == [False] * 6 + [True]
    assert drive.resets_seen == 1


def test_persistent_fault_toggles_bit7_never_high_twice() -> None:
    drive = FakeDrive(cia402.FAULT)
    drive.fault_present = True
    stepper = Cia402Stepper()
    trace = run(stepper, drive, 10)
    assert [cw for _, cw, _ in trace] == [0x00, 0x80] * 5
    assert drive.resets_seen == 5  # every 0x80 was a rising edge the drive saw
    assert not any(allowed for _, _, allowed in trace)
    drive.fault_present = False
    trace = run(stepper, drive, 6)
    assert trace[-1] == (cia402.OPERATION_ENABLED, 0x0F, True)


def test_fault_reset_low_ticks() -> None:
    drive = FakeDrive(cia402.FAULT)
    drive.fault_present = True
    trace = run(Cia402Stepper(reset_low_ticks=3), drive, 8)
    assert [cw for _, cw, _ in trace] == [0x00, 0x00, 0x00, 0x80] * 2


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_reset_low_ticks_validation(bad: object) -> None:
    with pytest.raises(ValueError, match="reset_low_ticks"):
        Cia402Stepper(reset_low_ticks=bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("lag", [0, 1, 2])
def test_fault_recovery_with_statusword_lag(lag: int) -> None:
    drive = FakeDrive(cia402.FAULT, lag=lag)
    trace = run(Cia402Stepper(), drive, 25)
    assert _never_two_resets_in_a_row(trace)
    assert trace[-1] == (cia402.OPERATION_ENABLED, 0x0F, True)


def test_quick_stop_latch_from_operation_enabled() -> None:
    drive = FakeDrive(cia402.SWITCHED_ON, qs_ramp_ticks=3)
    stepper = Cia402Stepper()
    run(stepper, drive, 2)
    assert stepper.torque_allowed
    stepper.request_stop()
    assert stepper.stop_requested and not stepper.torque_allowed  # at once, before a step
    trace = run(stepper, drive, 8)
    assert trace == [
        (cia402.OPERATION_ENABLED, 0x02, False),  # quick stop, transition 11
        (cia402.QUICK_STOP_ACTIVE, 0x02, False),  # ramping down
        (cia402.QUICK_STOP_ACTIVE, 0x02, False),
        (cia402.QUICK_STOP_ACTIVE, 0x02, False),  # ramp done: drive goes on by itself (12)
        (cia402.SWITCH_ON_DISABLED, 0x00, False),  # then disable voltage, for good
        (cia402.SWITCH_ON_DISABLED, 0x00, False),
        (cia402.SWITCH_ON_DISABLED, 0x00, False),
        (cia402.SWITCH_ON_DISABLED, 0x00, False),
    ]
    assert drive.state == cia402.SWITCH_ON_DISABLED


@pytest.mark.parametrize("state", [cia402.READY_TO_SWITCH_ON, cia402.SWITCHED_ON])
def test_quick_stop_latch_before_enabled(state: str) -> None:
    drive = FakeDrive(state)
    stepper = Cia402Stepper()
    stepper.request_stop()
    trace = run(stepper, drive, 3)
    assert [cw for _, cw, _ in trace] == [0x02, 0x00, 0x00]  # transitions 7 / 10
    assert drive.state == cia402.SWITCH_ON_DISABLED


def test_quick_stop_latch_never_resets_a_fault() -> None:
    drive = FakeDrive(cia402.FAULT)
    stepper = Cia402Stepper()
    stepper.request_stop()
    trace = run(stepper, drive, 6)
    assert all(cw == 0x02 for _, cw, _ in trace)
    assert drive.state == cia402.FAULT and drive.resets_seen == 0


def test_drive_initiated_quick_stop_is_left_by_disable_voltage() -> None:
    drive = FakeDrive(cia402.QUICK_STOP_ACTIVE, qs_ramp_ticks=None)  # option code 5..8
    trace = run(Cia402Stepper(), drive, 6)
    assert [cw for _, cw, _ in trace] == [0x00, 0x06, 0x07, 0x0F, 0x0F, 0x0F]
    assert trace[-1][2] is True


@given(st.lists(UINT16, max_size=60), st.integers(0, 60), st.integers(1, 4))
def test_any_statusword_sequence_keeps_the_invariants(
    statuswords: list[int], stop_at: int, reset_low_ticks: int
) -> None:
    stepper = Cia402Stepper(reset_low_ticks=reset_low_ticks)
    prev = 0
    for k, sw in enumerate(statuswords):
        if k == stop_at:
            stepper.request_stop()
        cw = stepper.step(sw)
        assert cw in (0x00, 0x02, 0x06, 0x07, 0x0F, 0x80)
        assert not (cw & 0x80 and prev & 0x80)
        if stepper.stop_requested:
            assert cw in (0x00, 0x02)
        enabled = decode_statusword(sw) == cia402.OPERATION_ENABLED
        assert stepper.torque_allowed == (enabled and not stepper.stop_requested)
        prev = cw
