"""Pure CANopen frame codecs and unit conversions for CiA 402 drives (no bus, no I/O).

Frames follow the CiA 301 predefined connection set and the PDO mapping the CAN backend
configures on every drive (all CANopen data is little-endian):

    RPDO1 0x200+node, master -> drive, 4 B: controlword 0x6040 u16 | target torque 0x6071 i16
    TPDO1 0x180+node, drive -> master, 8 B: position actual 0x6064 i32 | velocity actual 0x606C i32
    TPDO2 0x280+node, drive -> master, 4 B: statusword 0x6041 u16 | torque actual 0x6077 i16

Encoders write into caller-owned, preallocated bytearrays with precompiled ``struct.Struct``
objects (the moteus / canopen style), so the 1 kHz path builds no frame buffers. Decoders check
the length first: a frame shorter than its object (or, for EMCY and heartbeat, of any other
length) raises ``CanFrameError`` (both a ``ValueError`` and a ``BackendError``, so the CLI
prints it as one line) naming the object and both lengths. A PDO longer than its mapping is
read from its mapped leading bytes, as CiA 301 has a PDO consumer do (``pdo_excess`` tells
the caller, who counts them).

Sign convention (owned here): ``JointUnits.direction`` maps the motor sense to the joint sense
for position, velocity and torque alike, so mechanical power is the same number in both frames.
"""

import math
import numbers
import operator
import struct
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

from teleop_rt.errors import BackendError

Buffer = bytes | bytearray | memoryview

INT16_MIN = -0x8000
INT16_MAX = 0x7FFF

# --- COB-IDs, CiA 301 predefined connection set ------------------------------------------
COB_ID_NMT = 0x000
COB_ID_SYNC = 0x080
_EMCY_BASE = 0x080
_TPDO1_BASE = 0x180
_RPDO1_BASE = 0x200
_TPDO2_BASE = 0x280
_HEARTBEAT_BASE = 0x700  # NMT error control: heartbeat, boot-up, node guarding


def check_node_id(node_id: int) -> int:
    """Return ``node_id`` if it is a valid CANopen node id (1..127), else raise ValueError."""
    try:
        value = operator.index(node_id)  # ints and numpy ints; rejects floats and strings
    except TypeError:
        value = None
    if isinstance(node_id, bool) or value is None or not 1 <= value <= 127:
        raise ValueError(f"CANopen node id must be an integer in 1..127, got {node_id!r}")
    return value


def emcy_cob_id(node_id: int) -> int:
    """COB-ID of the node's emergency object (0x080 + node)."""
    return _EMCY_BASE + check_node_id(node_id)


def tpdo1_cob_id(node_id: int) -> int:
    """COB-ID of TPDO1, drive -> master (0x180 + node)."""
    return _TPDO1_BASE + check_node_id(node_id)


def tpdo3_cob_id(node_id: int) -> int:
    """COB-ID of TPDO3, drive -> master (0x380 + node)."""
    return 0x380 + check_node_id(node_id)


def rpdo1_cob_id(node_id: int) -> int:
    """COB-ID of RPDO1, master -> drive (0x200 + node)."""
    return _RPDO1_BASE + check_node_id(node_id)


def tpdo2_cob_id(node_id: int) -> int:
    """COB-ID of TPDO2, drive -> master (0x280 + node)."""
    return _TPDO2_BASE + check_node_id(node_id)


def heartbeat_cob_id(node_id: int) -> int:
    """COB-ID of NMT error control: heartbeat / boot-up / node guarding (0x700 + node)."""
    return _HEARTBEAT_BASE + check_node_id(node_id)


# --- frame layouts -------------------------------------------------------------------------
class CanFrameError(BackendError, ValueError):
    """A received CAN frame does not fit the object it should carry."""


RPDO1_STRUCT = struct.Struct("<Hh")  # 0x6040 controlword, 0x6071 target torque
TPDO1_STRUCT = struct.Struct("<ii")  # 0x6064 position actual, 0x606C velocity actual
TPDO2_STRUCT = struct.Struct("<Hh")  # 0x6041 statusword, 0x6077 torque actual
TPDO3_STRUCT = struct.Struct("<I")  # 0x60FD digital inputs (on a drive carrying an input)
EMCY_STRUCT = struct.Struct("<HB5s")  # CiA 301: error code, error register 0x1001, vendor bytes

RPDO1_NAME = "RPDO1 (0x6040 controlword u16 + 0x6071 target torque i16)"
TPDO1_NAME = "TPDO1 (0x6064 position actual i32 + 0x606C velocity actual i32)"
TPDO2_NAME = "TPDO2 (0x6041 statusword u16 + 0x6077 torque actual i16)"
TPDO3_NAME = "TPDO3 (0x60FD digital inputs u32)"
EMCY_NAME = "EMCY (error code u16 + error register u8 + 5 manufacturer bytes)"
HEARTBEAT_NAME = "heartbeat (NMT state u8)"


def _check_length(obj: str, expected: int, data: Buffer) -> None:
    # Called on the cyclic path: the f-string is built only when the frame is bad.
    if len(data) != expected:
        raise CanFrameError(f"{obj}: expected {expected} data bytes, received {len(data)}")


def pdo_excess(obj: str, mapped: int, data: Buffer) -> int:
    """Bytes a PDO carries beyond its ``mapped`` length (CiA 301: the consumer uses the mapped
    leading bytes); ``CanFrameError`` naming ``obj`` if it carries fewer."""
    extra = len(data) - mapped
    if extra < 0:
        raise CanFrameError(f"{obj}: expected {mapped} data bytes, received {len(data)}")
    return extra


def _pack(layout: struct.Struct, obj: str, buf: bytearray, a: int, b: int) -> None:
    # Exact size: a longer buffer would put trailing bytes on the bus as a wrong-length PDO.
    if len(buf) != layout.size:
        raise ValueError(f"{obj}: buffer must be {layout.size} bytes, got {len(buf)}")
    try:
        layout.pack_into(buf, 0, a, b)
    except struct.error as exc:  # out-of-range or non-integer value: one clear line
        raise ValueError(f"{obj}: cannot pack ({a!r}, {b!r}): {exc}") from None


def pack_rpdo1(buf: bytearray, controlword: int, torque_permille: int) -> None:
    """Write RPDO1 into ``buf`` (4 bytes): controlword u16, target torque i16 in per-mille."""
    _pack(RPDO1_STRUCT, RPDO1_NAME, buf, controlword, torque_permille)


def unpack_rpdo1(data: Buffer) -> tuple[int, int]:
    """Decode RPDO1 -> (controlword, target torque per-mille); the drive emulator's side.
    A longer PDO: its leading 4 bytes (as for every PDO decoder here)."""
    pdo_excess(RPDO1_NAME, RPDO1_STRUCT.size, data)
    return RPDO1_STRUCT.unpack_from(data)


def pack_tpdo1(buf: bytearray, counts: int, velocity: int) -> None:
    """Write TPDO1 into ``buf`` (8 bytes); the drive emulator's side."""
    _pack(TPDO1_STRUCT, TPDO1_NAME, buf, counts, velocity)


def unpack_tpdo1(data: Buffer) -> tuple[int, int]:
    """Decode TPDO1 -> (position actual in counts, velocity actual in drive velocity units)."""
    pdo_excess(TPDO1_NAME, TPDO1_STRUCT.size, data)
    return TPDO1_STRUCT.unpack_from(data)


def pack_tpdo2(buf: bytearray, statusword: int, torque_permille: int) -> None:
    """Write TPDO2 into ``buf`` (4 bytes); the drive emulator's side."""
    _pack(TPDO2_STRUCT, TPDO2_NAME, buf, statusword, torque_permille)


def unpack_tpdo2(data: Buffer) -> tuple[int, int]:
    """Decode TPDO2 -> (statusword, torque actual in per-mille of rated motor torque)."""
    pdo_excess(TPDO2_NAME, TPDO2_STRUCT.size, data)
    return TPDO2_STRUCT.unpack_from(data)


class Emcy(NamedTuple):
    """A decoded CiA 301 emergency message."""

    error_code: int  # CiA 301/402 error code; 0x00xx = error reset / no error
    error_register: int  # copy of object 0x1001 (bit 0 generic, 1 current, 2 voltage, ...)
    manufacturer: bytes  # 5 manufacturer-specific bytes

    @property
    def is_reset(self) -> bool:
        """True for the "error reset / no error" EMCY a node sends when its faults clear."""
        return self.error_code & 0xFF00 == 0

    def describe(self) -> str:
        """One line for logs and error messages (error classes from canopen's CiA 301 table)."""
        from canopen.emcy import EmcyError  # lazy: pulls in python-can; never on the tick path

        kind = next((d for c, m, d in EmcyError.DESCRIPTIONS if self.error_code & m == c), "")
        kind = f" ({kind})" if kind else ""
        return (
            f"EMCY 0x{self.error_code:04X}{kind}, error register 0x{self.error_register:02X}, "
            f"manufacturer data {self.manufacturer.hex(' ')}"
        )


def decode_emcy(data: Buffer) -> Emcy:
    """Decode an EMCY frame (8 bytes)."""
    _check_length(EMCY_NAME, EMCY_STRUCT.size, data)
    return Emcy._make(EMCY_STRUCT.unpack(data))


NMT_STATE_NAMES: dict[int, str] = {
    0x00: "BOOT-UP",
    0x04: "STOPPED",
    0x05: "OPERATIONAL",
    0x7F: "PRE-OPERATIONAL",
}


def decode_heartbeat(data: Buffer) -> str:
    """Decode a heartbeat / boot-up frame (1 byte) to the NMT state name.

    Bit 7 is masked off: it is 0 in heartbeats and the toggle bit in node-guarding replies,
    which share the COB-ID. An unknown state raises ``CanFrameError``.
    """
    _check_length(HEARTBEAT_NAME, 1, data)
    state = data[0] & 0x7F
    name = NMT_STATE_NAMES.get(state)
    if name is None:
        raise CanFrameError(f"{HEARTBEAT_NAME}: unknown NMT state 0x{state:02X}")
    return name


# SocketCAN's error classes (linux/can/error.h), which python-can passes on as an error frame's
# arbitration id; other interfaces use codes of their own, shown as the bare number.
_ERROR_CLASSES = (
    (0x040, "bus off"),
    (0x100, "controller restarted"),
    (0x020, "no ACK on transmission"),
    (0x010, "transceiver status"),
    (0x004, "controller problem"),
    (0x008, "protocol violation"),
    (0x080, "bus error"),
    (0x001, "TX timeout"),
    (0x002, "lost arbitration"),
    (0x200, "error counters"),
)
_CONTROLLER_PROBLEMS = (  # data[1] of a controller-problem frame
    (0x01, "RX buffer overflow"),
    (0x02, "TX buffer overflow"),
    (0x04, "RX error warning"),
    (0x08, "TX error warning"),
    (0x10, "RX error passive"),
    (0x20, "TX error passive"),
    (0x40, "back to error active"),
)


# What a working bus reports too: a frame that lost arbitration is sent again by the controller
# itself, the error counters and the error-warning levels (96 errors) say the counters rose
# while frames still flow. A bus that degrades further reports a class outside these (error
# passive, bus off, no ACK, ...) or stops delivering feedback, and both stop the session.
_WARNING_CLASSES = 0x002 | 0x200
_WARNING_CONTROLLER_PROBLEMS = 0x04 | 0x08 | 0x40


def error_frame_is_fault(error_id: int, data: Buffer) -> bool:
    """False only for an error frame whose every class (read as SocketCAN's) is a warning:
    lost arbitration, error counters, a controller problem that is only an error warning or
    back to error active. An unspecified controller problem or a code of another interface
    (no SocketCAN class) is a fault."""
    if not error_id or error_id & ~(_WARNING_CLASSES | 0x004):
        return True
    if error_id & 0x004:
        detail = data[1] if len(data) > 1 else 0
        return not detail or bool(detail & ~_WARNING_CONTROLLER_PROBLEMS)
    return False


def describe_error_frame(error_id: int, data: Buffer) -> str:
    """One line for a CAN error frame: its id and, read as SocketCAN's, the error classes."""
    names = [name for bit, name in _ERROR_CLASSES if error_id & bit]
    if error_id & 0x004 and len(data) > 1:
        problems = [name for bit, name in _CONTROLLER_PROBLEMS if data[1] & bit]
        if problems:
            names[names.index("controller problem")] += f": {', '.join(problems)}"
    detail = f" ({'; '.join(names)})" if names else ""
    return f"CAN error frame 0x{error_id:03X}{detail}"


# --- units ---------------------------------------------------------------------------------
VelocityUnit = Literal["rpm", "counts_per_s"]
_VELOCITY_UNITS = ("rpm", "counts_per_s")
_SATURATED_HIGH = (INT16_MAX, True)  # preallocated: the saturating path returns no new tuple
_SATURATED_LOW = (INT16_MIN, True)


def rated_torque_nm(od_0x6076: int, unit_nm: float = 1e-3) -> float:
    """Motor rated torque in N m from object 0x6076 (UNSIGNED32).

    CiA 402 gives 0x6076 in mN m (``unit_nm=1e-3``). Check the drive's firmware manual: a
    vendor that deviates (e.g. uN m) needs ``unit_nm=1e-6``.
    """
    if isinstance(od_0x6076, bool) or not isinstance(od_0x6076, numbers.Integral):
        raise ValueError(f"0x6076 motor rated torque must be an integer, got {od_0x6076!r}")
    if not 0 < od_0x6076 <= 0xFFFFFFFF:
        raise ValueError(f"0x6076 motor rated torque must be in 1..2**32-1, got {od_0x6076}")
    return int(od_0x6076) * unit_nm


@dataclass(frozen=True)
class JointUnits:
    """Drive units <-> joint SI units for one joint through an ideal gearbox.

    The gearbox is ideal (lossless, rigid, no backlash): joint angle = motor angle / gear_ratio
    and joint torque = motor torque * gear_ratio. ``direction`` multiplies all three of
    position, velocity and torque.

    Parameters:
        counts_per_rev: encoder counts per motor revolution (after quadrature), > 0.
        gear_ratio: motor revolutions per joint revolution, > 0.
        rated_torque_nm: motor rated torque in N m (0x6076; see ``from_od``), > 0.
        direction: +1 if positive motor rotation is positive joint rotation, else -1.
        velocity_unit: unit of 0x606C velocity actual: "rpm" (motor rpm, the EPOS4 default)
            or "counts_per_s" (encoder counts per second).
    """

    counts_per_rev: float
    gear_ratio: float
    rated_torque_nm: float
    direction: int = 1
    velocity_unit: VelocityUnit = "rpm"
    # Scale factors fixed at construction so every conversion is one multiply.
    _rad_per_count: float = field(init=False, repr=False, compare=False)
    _rad_s_per_velocity: float = field(init=False, repr=False, compare=False)
    _permille_per_nm: float = field(init=False, repr=False, compare=False)
    _nm_per_permille: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("counts_per_rev", "gear_ratio", "rated_torque_nm"):
            value = getattr(self, name)
            ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
            if not (ok and math.isfinite(value) and value > 0):
                raise ValueError(f"JointUnits.{name} must be a finite number > 0, got {value!r}")
        if isinstance(self.direction, bool) or self.direction not in (1, -1):
            raise ValueError(f"JointUnits.direction must be +1 or -1, got {self.direction!r}")
        if self.velocity_unit not in _VELOCITY_UNITS:
            raise ValueError(
                f"JointUnits.velocity_unit must be one of {_VELOCITY_UNITS}, "
                f"got {self.velocity_unit!r}"
            )
        d = float(self.direction)
        rad_per_count = d * 2.0 * math.pi / (self.counts_per_rev * self.gear_ratio)
        if self.velocity_unit == "rpm":
            rad_s_per_velocity = d * 2.0 * math.pi / (60.0 * self.gear_ratio)
        else:
            rad_s_per_velocity = rad_per_count
        joint_rated_nm = self.rated_torque_nm * self.gear_ratio
        set_ = object.__setattr__  # frozen dataclass: derived fields are set once, here
        set_(self, "_rad_per_count", rad_per_count)
        set_(self, "_rad_s_per_velocity", rad_s_per_velocity)
        set_(self, "_permille_per_nm", d * 1000.0 / joint_rated_nm)
        set_(self, "_nm_per_permille", d * joint_rated_nm / 1000.0)

    @classmethod
    def from_od(
        cls,
        counts_per_rev: float,
        gear_ratio: float,
        od_0x6076: int,
        direction: int = 1,
        velocity_unit: VelocityUnit = "rpm",
        unit_nm: float = 1e-3,
    ) -> "JointUnits":
        """Build from raw 0x6076 rated torque (mN m per CiA 402, see ``rated_torque_nm``)."""
        return cls(
            counts_per_rev,
            gear_ratio,
            rated_torque_nm(od_0x6076, unit_nm),
            direction,
            velocity_unit,
        )

    def counts_to_rad(self, counts: int) -> float:
        """Position actual 0x6064 (motor encoder counts) -> joint angle in rad."""
        return counts * self._rad_per_count

    def velocity_to_rad_s(self, velocity: int) -> float:
        """Velocity actual 0x606C (motor rpm or counts/s, per ``velocity_unit``) -> joint rad/s."""
        return velocity * self._rad_s_per_velocity

    def torque_nm_to_permille(self, tau_nm: float) -> tuple[int, bool]:
        """Joint N m -> (0x6071 target torque in per-mille of rated motor torque, saturated).

        permille = direction * 1000 * tau_nm / (gear_ratio * rated_torque_nm), rounded to the
        nearest integer and clamped to the int16 range; ``saturated`` is True when it had to be
        clamped, i.e. the request was half a per-mille or more beyond [-32768, 32767]. NaN
        raises ValueError: an undefined torque must not reach a drive as some number.
        """
        x = tau_nm * self._permille_per_nm
        if x >= INT16_MAX + 0.5:
            return _SATURATED_HIGH
        if x <= INT16_MIN - 0.5:
            return _SATURATED_LOW
        if x != x:
            raise ValueError(f"joint torque is NaN (tau_nm={tau_nm!r})")
        return round(x), False

    def permille_to_torque_nm(self, permille: int) -> float:
        """Torque actual 0x6077 (per-mille of rated motor torque) -> joint torque in N m."""
        return permille * self._nm_per_permille
