"""The ``can:`` section of a session config: buses, drives, torque sensors, timing (strict).

Bus settings are python-can's own keyword arguments (``interface``, ``channel``, ``bitrate`` and
any further ``options``), so the same section points at SocketCAN, PCAN, Kvaser, … or at the
drive emulator (``udp_multicast`` across processes, ``virtual`` in one process).

Importing this module must stay cheap (teleop_rt.config imports it): pydantic only, no
python-can, no canopen.

EDS paths: a relative ``eds`` is resolved against the config file's folder when the config is
loaded (``CanSpec.with_paths_resolved``, like the URDFs); a missing file is a ``ConfigError``
naming the key when the backend or the emulator is built (``CanSideSpec.check_eds``), so a
``can:`` section only fails a session that drives CAN.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from teleop_rt.errors import ConfigError
from teleop_rt.inputs import file_problem, shown
from teleop_rt.schema import StrictModel

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
NodeId = Annotated[int, Field(ge=1, le=127)]
CobId = Annotated[int, Field(ge=0x001, le=0x7FF)]
OptionValue = str | int | float | bool

DEFAULT_EDS = Path(__file__).resolve().parent / "od" / "cia402_drive.eds"
LOCAL_HOP_LIMIT = 0  # udp_multicast: a multicast TTL of 0 never leaves this host


_Strict = StrictModel  # unknown keys refused, no boolean taken as a number


class CanBusSpec(_Strict):
    """One CAN bus, in python-can's terms: ``can.Bus(interface=, channel=, bitrate=, **options)``.

    Examples: ``{interface: socketcan, channel: can0}`` (bitrate set with ``ip link``),
    ``{interface: pcan, channel: PCAN_USBBUS1, bitrate: 1000000}``,
    ``{interface: udp_multicast, channel: 239.74.163.1, options: {port: 43113, hop_limit: 0}}``
    (the emulator in another process).

    ``udp_multicast`` gets ``hop_limit: 0`` unless the options give one: python-can's default
    (a multicast TTL of 1) sends every frame out on the machine's network interface, a TTL of
    0 keeps it on this host.
    """

    interface: str
    channel: str | int | None = None
    bitrate: Annotated[int, Field(ge=10_000, le=1_000_000)] | None = None
    options: dict[str, OptionValue] = Field(default_factory=dict)

    def kwargs(self) -> dict[str, Any]:  # python-can's Bus takes any of its options
        """Keyword arguments for ``can.Bus``."""
        out: dict[str, OptionValue] = {"interface": self.interface}
        if self.channel is not None:
            out["channel"] = self.channel
        if self.bitrate is not None:
            out["bitrate"] = self.bitrate
        if self.interface == "udp_multicast":
            out["hop_limit"] = LOCAL_HOP_LIMIT
        out.update(self.options)
        return out


class DriveSpec(_Strict):
    """One joint's CiA 402 drive: node id and the unit conversion motor <-> joint.

    ``q = direction * 2 pi counts / (counts_per_rev * gear_ratio) + zero_offset_rad``; joint
    torque = direction * gear_ratio * rated torque (0x6076, read from the drive) * per-mille /
    1000. ``rated_torque_unit_nm`` is the unit of 0x6076 (CiA 402: mN m = 0.001).
    """

    node_id: NodeId
    counts_per_rev: PositiveFloat
    gear_ratio: PositiveFloat = 1.0
    direction: Literal[1, -1] = 1
    velocity_unit: Literal["rpm", "counts_per_s"] = "rpm"
    zero_offset_rad: FiniteFloat = 0.0
    rated_torque_unit_nm: PositiveFloat = 1e-3
    max_torque_permille: Annotated[int, Field(ge=1, le=0xFFFF)] | None = None  # 0x6072
    # the drive's EDS (relative: to the config file's folder); default: the bundled CiA 402 EDS
    eds: Path | None = None

    def with_eds_resolved(self, base_dir: Path) -> DriveSpec:
        if self.eds is None or self.eds.is_absolute():
            return self
        return self.model_copy(update={"eds": (base_dir / self.eds).resolve()})


class TorqueSensorSpec(_Strict):
    """External joint torque from a sensor node's TPDO (the paper's strain gauges).

    The frame carries one little-endian integer per joint (``dtype``) in joint order (or the
    ``channels`` given); tau_ext[j] = scale_nm[j] * (raw - offset), the offset being the mean
    over the first ``zero_ticks`` ticks of start-up, while the robot rests (drives disabled).
    ``scale_nm`` is N m per count and its sign maps the sensor sense to tau_ext (the torque
    the world applies to the robot, see teleop_rt.control).
    """

    cob_id: CobId
    dtype: Literal["int16", "int32"] = "int16"
    scale_nm: FiniteFloat | list[FiniteFloat] = 0.001
    channels: list[Annotated[int, Field(ge=0, le=3)]] | None = None
    zero_ticks: Annotated[int, Field(ge=0, le=60_000)] = 500

    @model_validator(mode="after")
    def _nonzero_scale(self) -> TorqueSensorSpec:
        scales = self.scale_nm if isinstance(self.scale_nm, list) else [self.scale_nm]
        if any(s == 0 for s in scales):
            raise ValueError("scale_nm: must not be 0")
        return self


class DigitalInputSpec(_Strict):
    """One bit of a drive's digital inputs (CiA 402 0x60FD: bit 0 negative limit, 1 positive
    limit, 2 home, 16-31 manufacturer-specific), mapped in the drive's TPDO3 every SYNC."""

    drive: NodeId  # the node id of one of this bus's drives
    bit: Annotated[int, Field(ge=0, le=31)]


class CanSideSpec(_Strict):
    """One robot: its own bus, one drive per joint (in joint order), an optional sensor, and
    the operator's clutch and presence (dead-man) inputs (HSI only, off unless given:
    teleop_rt.mapping reads them each tick)."""

    bus: CanBusSpec
    drives: list[DriveSpec] = Field(min_length=1)
    torque_sensor: TorqueSensorSpec | None = None
    clutch_input: DigitalInputSpec | None = None  # bit set: the clutch is pressed
    presence_input: DigitalInputSpec | None = None  # bit set: the operator is present

    def inputs(self) -> dict[str, DigitalInputSpec]:
        """The digital inputs given, by key."""
        given = {"clutch_input": self.clutch_input, "presence_input": self.presence_input}
        return {k: v for k, v in given.items() if v is not None}

    @model_validator(mode="after")
    def _unique_ids(self) -> CanSideSpec:
        ids = [d.node_id for d in self.drives]
        if len(set(ids)) != len(ids):
            raise ValueError(f"drives: node ids must be unique on a bus, got {ids}")
        for key, spec in self.inputs().items():
            if spec.drive not in ids:
                raise ValueError(
                    f"{key}.drive: node {spec.drive} is not one of this bus's drives {ids}"
                )
        if self.torque_sensor is not None:
            cob = self.torque_sensor.cob_id
            own = {f(i) for i in ids for f in _DRIVE_COBS}
            if cob in own or cob == 0x080:
                raise ValueError(f"torque_sensor.cob_id 0x{cob:03X} collides with a drive's")
        return self

    def check_eds(self, key: str) -> None:
        """ConfigError naming the first drive whose EDS file is missing (``key``: 'can.hsi')."""
        for j, d in enumerate(self.drives):
            if d.eds is None:
                continue
            problem = file_problem(d.eds)
            if problem == "no such file":
                raise ConfigError(f"{key}.drives.{j}.eds: no such file: {shown(d.eds)}")
            if problem is not None:
                raise ConfigError(f"{key}.drives.{j}.eds: {shown(d.eds)}: {problem}")


_DRIVE_COBS = (
    lambda i: 0x080 + i,  # EMCY
    lambda i: 0x180 + i,  # TPDO1
    lambda i: 0x200 + i,  # RPDO1
    lambda i: 0x280 + i,  # TPDO2
    lambda i: 0x380 + i,  # TPDO3 (digital inputs)
    lambda i: 0x580 + i,  # SDO
    lambda i: 0x600 + i,
    lambda i: 0x700 + i,  # heartbeat
)


def _emulated_side(channel: str, port: int) -> CanSideSpec:
    return CanSideSpec(
        bus=CanBusSpec(
            interface="udp_multicast",
            channel=channel,
            options={"port": port, "hop_limit": LOCAL_HOP_LIMIT},
        ),
        drives=[
            DriveSpec(node_id=1, counts_per_rev=4096, gear_ratio=20, velocity_unit="counts_per_s"),
            DriveSpec(node_id=2, counts_per_rev=4096, gear_ratio=20, velocity_unit="counts_per_s"),
        ],
        torque_sensor=TorqueSensorSpec(cob_id=0x18A, dtype="int32", scale_nm=1e-5),
    )


class CanSpec(_Strict):
    """The CAN backend (teleop_rt.hal.can.backend): one bus per robot plus protocol timing.

    With no ``can:`` section the defaults describe the drive emulator's robots
    (tools/drive_emulator.py) over ``udp_multicast`` on this host.
    """

    hsi: CanSideSpec = Field(default_factory=lambda: _emulated_side("239.74.163.1", 43113))
    to: CanSideSpec = Field(default_factory=lambda: _emulated_side("239.74.163.2", 43114))
    master_node_id: NodeId = 127  # the master's own heartbeat is 0x700 + this
    heartbeat_ms: Annotated[int, Field(ge=1, le=10_000)] = 100  # drives produce (0x1017)
    heartbeat_timeout_ms: Annotated[int, Field(ge=2, le=30_000)] = 150  # master declares lost
    master_heartbeat_ms: Annotated[int, Field(ge=1, le=10_000)] = 50  # master produces
    master_heartbeat_timeout_ms: Annotated[int, Field(ge=2, le=30_000)] = 200  # 0x1016 on drives
    comm_loss_reaction: Annotated[int, Field(ge=0, le=3)] = 1  # 0x6007: 1 = fault (torque off)
    quick_stop_option: Annotated[int, Field(ge=1, le=4)] = 2  # 0x605A: stop, then disable
    status_every_sync: Annotated[int, Field(ge=1, le=3)] = 2  # TPDO2 transmission type
    # RPDO1 transmission type: 'sync' (1, CiA 402's cyclic synchronous modes: the target takes
    # effect at the next SYNC, one tick after the feedback it was computed from) or 'async'
    # (255: at once on reception, if the drive supports it in CST mode)
    rpdo_transmission: Literal["sync", "async"] = "sync"
    feedback_window_us: Annotated[int, Field(ge=50, le=100_000)] = 600  # after SYNC
    missed_feedback_ticks: Annotated[int, Field(ge=1, le=100_000)] = 3
    nmt_reset_at_start: Literal["node", "communication", "none"] = "node"
    boot_timeout_s: PositiveFloat = 5.0
    sdo_timeout_s: PositiveFloat = 0.5
    enable_timeout_ticks: Annotated[int, Field(ge=10, le=60_000)] = 2000
    stop_ticks: Annotated[int, Field(ge=1, le=10_000)] = 100  # quick stop, at most
    disable_ticks: Annotated[int, Field(ge=1, le=10_000)] = 20  # then disable voltage, at most
    emulate: bool = False  # in-process drive emulator on a virtual bus (tests, demos)

    @model_validator(mode="after")
    def _timeouts(self) -> CanSpec:
        if self.heartbeat_timeout_ms <= self.heartbeat_ms:
            raise ValueError("heartbeat_timeout_ms: must exceed heartbeat_ms")
        if self.master_heartbeat_timeout_ms <= self.master_heartbeat_ms:
            raise ValueError("master_heartbeat_timeout_ms: must exceed master_heartbeat_ms")
        if self.to.inputs():  # (the operator's inputs act on the HSI's map)
            key = next(iter(self.to.inputs()))
            raise ValueError(f"to.{key}: the operator's clutch and presence are the HSI's")
        return self

    def side(self, name: str) -> CanSideSpec:
        return self.hsi if name == "hsi" else self.to

    def with_paths_resolved(self, base_dir: Path) -> CanSpec:
        """Relative EDS paths resolved against ``base_dir`` (the config file's folder)."""
        update = {}
        for name in ("hsi", "to"):
            side = self.side(name)
            drives = [d.with_eds_resolved(base_dir) for d in side.drives]
            update[name] = side.model_copy(update={"drives": drives})
        return self.model_copy(update=update)
