"""A CiA 402 drive emulator: one robot's drives (and its torque sensor) on one CAN bus.

Each drive is a ``canopen.LocalNode`` built from an EDS (the bundled generic CiA 402 one by
default): the library serves SDO, NMT and EMCY; this module adds what a drive does around
them, clocked by the master's SYNC:

* the CiA 402 power state machine (controlword in, statusword out; quick stop, fault,
  fault reset on a rising edge of bit 7), cyclic synchronous torque (mode 10) only;
* PDOs as the master mapped them over SDO (0x1400/0x1600, 0x1800/0x1A00), compiled into
  ``struct`` layouts at NMT start; synchronous RPDOs take effect at the next SYNC, TPDOs go
  out every n-th SYNC (transmission type n), acyclic (0) on change, or on their event timer;
* heartbeat producer (0x1017) and consumer of the master's heartbeat (0x1016) with the
  communication-loss reaction 0x6007; EMCY on faults; boot-up after an NMT reset;
* the joint dynamics: the project's simulated plant (``teleop_rt.hal.sim``), advanced one
  period per SYNC with the torques the drives apply. The joints are held (brakes) until every
  drive is in OPERATION ENABLED; from then on the world clock runs.

Timing per SYNC k: the plant advances over the last period with the torque that was active
(latched at SYNC k-1), the drive samples position / velocity / statusword and sends its TPDOs,
then latches the RPDO received since SYNC k-1 (new controlword, new target torque). A torque
computed from the feedback of SYNC k therefore acts from SYNC k+1 on: one period of transport
delay, as on real drives in a SYNC cycle.

The emulator's clock is the SYNC count (``period_us`` per SYNC), so stepping it from the
master (``poll``, see ``SteppedBus``) is deterministic; run free (``serve``) it also advances
with the wall clock while no SYNC comes, and the heartbeats (the drives' own, 0x1017, and
their watch of the master's, 0x1016) follow the wall clock, as a real drive's do, however
fast or slow the SYNCs come.

Fault injection: ``inject(Fault(kind, node_id, at_tick, ticks))`` with kind one of
``drop_tpdo`` (a drive sends no TPDO), ``emcy`` (EMCY 0x2310 and FAULT), ``stop_heartbeat``,
``status_fault`` (FAULT in the statusword, no EMCY), ``error_frame`` (a CAN error frame),
``drop_sensor`` (the torque sensor sends nothing), ``long_tpdo`` (a drive's TPDOs shorter than
8 bytes carry one byte more than their mapping, as some drives pad them). ``at_tick`` counts
world ticks (SYNCs since the joints were released); None means the next SYNC.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import can
import canopen
from canopen import objectdictionary as odt

from teleop_rt.hal.can.codec import JointUnits, rated_torque_nm
from teleop_rt.hal.can.config import DEFAULT_EDS, CanSpec, DriveSpec, TorqueSensorSpec

if TYPE_CHECKING:
    from teleop_rt.config import SessionConfig
    from teleop_rt.hal.sim import SimBackend
    from teleop_rt.world import Load

log = logging.getLogger(__name__)

# CiA 402 states and their statuswords (bit 9 remote, bit 4 voltage enabled where it is)
NRTSO, SOD, RTSO, SO, OE, QSA, FRA, FAULT = (
    "NOT READY TO SWITCH ON",
    "SWITCH ON DISABLED",
    "READY TO SWITCH ON",
    "SWITCHED ON",
    "OPERATION ENABLED",
    "QUICK STOP ACTIVE",
    "FAULT REACTION ACTIVE",
    "FAULT",
)
STATUSWORD = {
    NRTSO: 0x0200,
    SOD: 0x0240,
    RTSO: 0x0231,
    SO: 0x0233,
    OE: 0x0237,
    QSA: 0x0217,
    FRA: 0x021F,
    FAULT: 0x0218,
}
MODE_CST = 10
EMCY_OVERCURRENT = 0x2310  # "continuous over current" (CiA 402)
EMCY_HEARTBEAT = 0x8130  # "life guard error or heartbeat error" (CiA 301)
EMCY_PDO_LENGTH = 0x8210  # "PDO not processed due to length error" (CiA 301)
_ONE_SHOT = ("emcy", "status_fault", "error_frame")
FAULT_KINDS = (
    "drop_tpdo", "emcy", "stop_heartbeat", "status_fault", "error_frame", "drop_sensor", "long_tpdo"
)  # fmt: skip

_FMT = {
    odt.INTEGER8: "b",
    odt.UNSIGNED8: "B",
    odt.INTEGER16: "h",
    odt.UNSIGNED16: "H",
    odt.INTEGER32: "i",
    odt.UNSIGNED32: "I",
}
_NMT_CODES = {"INITIALISING": 0x00, "STOPPED": 0x04, "OPERATIONAL": 0x05, "PRE-OPERATIONAL": 0x7F}
_NMT_START, _NMT_STOP, _NMT_PREOP, _NMT_RESET, _NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82


@dataclass
class Fault:
    """A fault to inject; see the module docstring for the kinds."""

    kind: str
    node_id: int | None = None  # None: every drive (error_frame / drop_sensor ignore it)
    at_tick: int | None = None  # world tick it starts at; None: the next SYNC
    ticks: int | None = None  # how long it lasts (drop_*, stop_heartbeat); None: for good

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {self.kind!r} (one of {', '.join(FAULT_KINDS)})")


@dataclass
class _Pdo:
    cob_id: int
    layout: struct.Struct
    objects: list[int]  # object indices, in frame order
    trans_type: int
    event_timer_us: int = 0
    counter: int = 0
    last_data: bytes = b""
    last_sent_us: int = 0


class EmulatedDrive:
    """One CiA 402 drive behind a ``canopen.LocalNode``."""

    def __init__(self, emu: DriveEmulator, spec: DriveSpec) -> None:
        self.emu = emu
        self.spec = spec
        self.node_id = spec.node_id
        od = canopen.import_od(str(spec.eds or DEFAULT_EDS), spec.node_id)
        self.node = canopen.LocalNode(spec.node_id, od)
        emu.network.add_node(self.node)
        # heartbeats come from the SYNC-driven clock below, not from python-can's threads
        self.node.nmt.start_heartbeat = self._set_heartbeat  # type: ignore[method-assign]
        self.node.nmt.stop_heartbeat = lambda: None  # type: ignore[method-assign]
        self.node.nmt.update_heartbeat = lambda: None  # type: ignore[method-assign]
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)
        self.sdo_writes: list[tuple[int, int, int]] = []  # (index, subindex, value) in order
        self.nmt_log: list[str] = []
        self.mapping_errors: list[str] = []
        # every RPDO taken at a SYNC: (controlword, target torque, state it was received in)
        self.commands: list[tuple[int, int, str]] = []
        # SYNCs a quick stop takes (QUICK STOP ACTIVE, decelerating) before SWITCH ON DISABLED
        self.quick_stop_syncs = 0
        # the drive's digital input pins (0x60FD, sampled at each SYNC): wires, not state, so
        # an NMT reset keeps them; a test sets bits here (the operator's clutch, presence)
        self.digital_inputs = 0
        self.power_on()

    # --- life cycle ---------------------------------------------------------------------
    def power_on(self) -> None:
        """State after power-up / NMT reset node: defaults from the EDS, SWITCH ON DISABLED."""
        self.node.data_store.clear()
        self.obj: dict[int, int] = {
            0x6040: 0,
            0x6041: STATUSWORD[SOD],
            0x6060: 0,
            0x6061: 0,
            0x6064: 0,
            0x606C: 0,
            0x6071: 0,
            0x6077: 0,
            0x60FD: self.digital_inputs,
            0x603F: 0,
            0x1001: 0,
        }
        self.state = SOD
        self._quick_stop_left = 0
        self._cw_prev = 0
        self.active_permille = 0
        self.heartbeat_us = 0
        self.last_heartbeat_us = 0
        self.watch_master_id = 0
        self.watch_timeout_us = 0
        self.master_seen_us: int | None = None
        self.rpdos: dict[int, _Pdo] = {}
        self.tpdos: list[_Pdo] = []
        self.pending: dict[int, int] = {}  # object -> value received since the last SYNC
        self.fault_cause: str | None = None
        rated = self._od_value(0x6076, 0)
        self.units = self._units(rated)
        self.max_torque = self._od_value(0x6072, 0)
        self.quick_stop_option = self._od_value(0x605A, 0)

    def _units(self, rated_raw: int) -> JointUnits:
        s = self.spec
        return JointUnits(
            s.counts_per_rev,
            s.gear_ratio,
            rated_torque_nm(rated_raw, s.rated_torque_unit_nm),
            s.direction,
            s.velocity_unit,
        )

    def _set_heartbeat(self, heartbeat_time_ms: int) -> None:
        self.heartbeat_us = int(heartbeat_time_ms) * 1000
        self.last_heartbeat_us = self.emu.heartbeat_clock_us() - self.heartbeat_us  # at once

    @property
    def nmt_state(self) -> str:
        return self.node.nmt.state

    # --- object dictionary --------------------------------------------------------------
    def _od_entry(self, index: int, subindex: int) -> odt.ODVariable:
        obj = self.node.object_dictionary[index]
        return obj if isinstance(obj, odt.ODVariable) else obj[subindex]

    def _od_value(self, index: int, subindex: int) -> int:
        # the drive's objects the emulator reads are integers (CiA 402's and 301's)
        raw = self.node.get_data(index, subindex)
        return cast(int, self._od_entry(index, subindex).decode_raw(raw))

    def _on_sdo_read(self, index: int, subindex: int, od: odt.ODVariable) -> int | None:
        return self.obj.get(index) if index in self.obj and index != 0x6060 else None

    def _on_sdo_write(self, index: int, subindex: int, od: odt.ODVariable, data: bytes) -> None:
        value = cast(int, od.decode_raw(data))  # every object written here is an integer
        self.sdo_writes.append((index, subindex, value))
        if index == 0x6060:
            self.obj[0x6060] = self.obj[0x6061] = value
        elif index == 0x6076:
            self.units = self._units(value)
        elif index == 0x6072:
            self.max_torque = value
        elif index == 0x605A:
            self.quick_stop_option = value
        elif index == 0x1016 and subindex == 1:
            self.watch_master_id = (value >> 16) & 0x7F
            self.watch_timeout_us = (value & 0xFFFF) * 1000
            self.master_seen_us = None  # monitoring starts with the first heartbeat

    # --- NMT --------------------------------------------------------------------------------
    def on_nmt(self, command: int) -> None:
        """Called after canopen's NmtSlave has taken the command."""
        self.nmt_log.append(
            {_NMT_START: "start", _NMT_STOP: "stop", _NMT_PREOP: "pre-op"}.get(
                command, "reset node" if command == _NMT_RESET else "reset communication"
            )
        )
        if command in (_NMT_RESET, _NMT_RESET_COMM):
            if command == _NMT_RESET:
                self.power_on()
            else:
                self._reset_communication()
            self.node.nmt.send_command(_NMT_RESET)  # boot-up frame (state INITIALISING) ...
            self.node.nmt.send_command(_NMT_PREOP)  # ... then PRE-OPERATIONAL, heartbeat on
        elif command == _NMT_START:
            self._compile_pdos()
        elif command in (_NMT_STOP, _NMT_PREOP):
            self.rpdos, self.tpdos = {}, []

    def _reset_communication(self) -> None:
        for index in list(self.node.data_store):
            if 0x1000 <= index < 0x2000:
                del self.node.data_store[index]
        self.heartbeat_us = 0
        self.watch_master_id = self.watch_timeout_us = 0
        self.rpdos, self.tpdos = {}, []

    def _compile_pdos(self) -> None:
        self.rpdos, self.tpdos = {}, []
        for n in range(4):
            pdo = self._compile(0x1400 + n, 0x1600 + n, f"RPDO{n + 1}")
            if pdo is not None:
                self.rpdos[pdo.cob_id] = pdo
            pdo = self._compile(0x1800 + n, 0x1A00 + n, f"TPDO{n + 1}")
            if pdo is not None:
                if 241 <= pdo.trans_type <= 253:
                    self.mapping_errors.append(f"TPDO{n + 1}: transmission type {pdo.trans_type}")
                else:
                    self.tpdos.append(pdo)

    def _compile(self, com: int, mapping: int, name: str) -> _Pdo | None:
        if com not in self.node.object_dictionary:
            return None
        cob = self._od_value(com, 1)
        if cob & 0x80000000:
            return None
        fmt, objects = "<", []
        for sub in range(1, self._od_value(mapping, 0) + 1):
            entry = self._od_value(mapping, sub)
            index, bits = entry >> 16, entry & 0xFF
            if index not in self.node.object_dictionary:
                self.mapping_errors.append(f"{name}: object 0x{index:04X} does not exist")
                return None
            var = self._od_entry(index, (entry >> 8) & 0xFF)
            code = None if var.data_type is None else _FMT.get(var.data_type)
            if code is None or struct.calcsize(code) * 8 != bits or not var.pdo_mappable:
                self.mapping_errors.append(f"{name}: cannot map 0x{index:04X} as {bits} bits")
                return None
            fmt += code
            objects.append(index)
        trans = self._od_value(com, 2)
        timer = self._od_value(com, 5) * 1000 if com >= 0x1800 else 0
        return _Pdo(cob & 0x7FF, struct.Struct(fmt), objects, trans, timer)

    # --- cyclic -------------------------------------------------------------------------------
    def on_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        if len(data) < pdo.layout.size:  # longer: the mapped leading bytes (CiA 301)
            self.emu.send(0x80 + self.node_id, struct.pack("<HB5s", EMCY_PDO_LENGTH, 0, b""))
            return
        for index, value in zip(pdo.objects, pdo.layout.unpack_from(data), strict=True):
            self.pending[index] = value
        if pdo.trans_type >= 254:  # asynchronous RPDO: takes effect at once
            self._latch()

    def sample(self, q: float, v: float) -> None:
        """Position / velocity / statusword / torque as measured at this SYNC."""
        u = self.units
        self.obj[0x6064] = round((q - self.spec.zero_offset_rad) / u.counts_to_rad(1))
        self.obj[0x606C] = round(v / u.velocity_to_rad_s(1))
        self.obj[0x6041] = STATUSWORD[self.state]
        self.obj[0x6077] = self.active_permille
        self.obj[0x60FD] = self.digital_inputs

    def tpdo_frames(self, now_us: int, out: list) -> None:
        """Append the TPDOs due at the SYNC of ``now_us`` to ``out`` as (cob_id, data)."""
        obj = self.obj
        for pdo in self.tpdos:
            data = pdo.layout.pack(*[obj[i] for i in pdo.objects])
            t = pdo.trans_type
            if 1 <= t <= 240:
                pdo.counter += 1
                due = pdo.counter >= t
                if due:
                    pdo.counter = 0
            elif t == 0:
                due = data != pdo.last_data
            else:
                due = pdo.event_timer_us > 0 and now_us - pdo.last_sent_us >= pdo.event_timer_us
            if due:
                pdo.last_data, pdo.last_sent_us = data, now_us
                out.append((pdo.cob_id, data))

    def advance_state(self) -> None:
        """Transitions the drive makes by itself, once per SYNC."""
        if self.state == FRA:
            self.state = FAULT
        elif self.state == QSA and 1 <= self.quick_stop_option <= 4:
            if self._quick_stop_left > 0:  # still decelerating
                self._quick_stop_left -= 1
            else:
                self.state = SOD  # stopped, then voltage off

    def _latch(self) -> None:
        pending = self.pending
        if 0x6071 in pending:
            self.obj[0x6071] = pending[0x6071]
        if 0x6040 in pending:
            self.obj[0x6040] = cw = pending[0x6040]
            self.commands.append((cw, self.obj[0x6071], self.state))
            self._controlword(cw)
        pending.clear()
        enabled = self.state == OE and self.obj[0x6061] == MODE_CST
        target = self.obj[0x6071] if enabled else 0
        limit = self.max_torque
        self.active_permille = max(-limit, min(limit, target))

    def latch(self) -> None:
        """At SYNC: the RPDO data received since the last SYNC takes effect."""
        self._latch()

    def _controlword(self, cw: int) -> None:
        prev, self._cw_prev = self._cw_prev, cw
        s = self.state
        if s == FAULT:
            if cw & 0x80 and not prev & 0x80:  # fault reset (the cause is transient here)
                self.state = SOD
                self.obj[0x603F] = self.obj[0x1001] = 0
                self.emu.send(0x80 + self.node_id, struct.pack("<HB5s", 0, 0, b""))
            return
        if s in (FRA, NRTSO) or cw & 0x80:
            return
        if cw & 0x02 == 0:  # disable voltage
            self.state = SOD
        elif cw & 0x06 == 0x02:  # quick stop
            self.state = QSA if s == OE else (SOD if s in (RTSO, SO) else s)
            if s == OE:
                self._quick_stop_left = self.quick_stop_syncs
        elif cw & 0x07 == 0x06:  # shutdown
            if s in (SOD, SO, OE):
                self.state = RTSO
        elif cw & 0x0F == 0x07:  # switch on / disable operation
            if s in (RTSO, OE):
                self.state = SO
        elif cw & 0x0F == 0x0F:  # enable operation
            if s == SO or (s == QSA and self.quick_stop_option >= 5):
                self.state = OE

    def fault(self, cause: str, emcy_code: int | None) -> None:
        """Enter FAULT REACTION ACTIVE (FAULT at the next SYNC); EMCY if a code is given."""
        if self.state in (FRA, FAULT):
            return
        self.state = FRA
        self.active_permille = 0
        self.fault_cause = cause
        self.obj[0x603F] = emcy_code or 0xFF00
        self.obj[0x1001] = 0x01
        if emcy_code is not None:
            self.emu.send(0x80 + self.node_id, struct.pack("<HB5s", emcy_code, 0x01, b""))

    def heartbeat(self, now_us: int, silent: bool) -> None:
        if self.heartbeat_us and now_us - self.last_heartbeat_us >= self.heartbeat_us:
            self.last_heartbeat_us = now_us
            if not silent:
                self.emu.send(0x700 + self.node_id, bytes([_NMT_CODES.get(self.nmt_state, 0x7F)]))

    def watch_master(self, now_us: int) -> None:
        if not self.watch_timeout_us or self.master_seen_us is None:
            return
        if now_us - self.master_seen_us > self.watch_timeout_us:
            self.master_seen_us = None  # one reaction per loss
            reaction = self._od_value(0x6007, 0)
            if reaction == 1:
                self.fault("master heartbeat lost", EMCY_HEARTBEAT)
            elif reaction == 2:
                self.state = SOD
            elif reaction == 3 and self.state == OE:
                self.state = QSA


class DriveEmulator:
    """The drives (and torque sensor) of one robot, sharing one bus and one simulated plant.

    Parameters:
        bus: a python-can bus of its own (the master uses another instance / process).
        cfg: the session config: the plant, its loads and the ``can:`` section (defaults if
            absent) come from it, so master and emulator agree on node ids and units.
        side: 'hsi' or 'to'.
        operator: replaces the config's operator model on the HSI (as for the sim backend).
        sensor_offset_nm: a constant bias of the emulated torque sensor (zeroed by the master).
        rated_torque_raw: 0x6076 of every emulated drive (mN m); None keeps the EDS default.
    """

    def __init__(
        self,
        bus: can.BusABC,
        cfg: SessionConfig,
        side: str,
        operator: Load | None = None,
        sensor_offset_nm: float | list[float] = 0.0,
        rated_torque_raw: int | None = None,
    ) -> None:
        self.bus = bus
        self.cfg = cfg
        self.side = side
        self.operator = operator
        spec = (cfg.can or CanSpec()).side(side)
        spec.check_eds(f"can.{side}")
        self.period_us = round(cfg.dt * 1e6)
        self.time_us = 0
        self._wall_origin: float | None = None  # set by ``serve``: heartbeats by the wall clock
        self.network = canopen.Network(bus)  # no notifier: poll() feeds it, one thread
        self.drives = [EmulatedDrive(self, d) for d in spec.drives]
        if rated_torque_raw is not None:
            for d in self.drives:
                rated = d.node.object_dictionary[0x6076]
                assert isinstance(rated, odt.ODVariable)  # 0x6076 is a variable in every EDS
                rated.default = rated_torque_raw
                d.power_on()
        self.by_node = {d.node_id: d for d in self.drives}
        self.sensor: TorqueSensorSpec | None = spec.torque_sensor
        n = len(self.drives)
        self.sensor_offset = (
            list(sensor_offset_nm) if isinstance(sensor_offset_nm, list) else [sensor_offset_nm] * n
        )
        if self.sensor is not None:
            s = self.sensor
            self._sensor_scale = s.scale_nm if isinstance(s.scale_nm, list) else [s.scale_nm] * n
            self._sensor_channels = s.channels or list(range(n))
            width = max(self._sensor_channels) + 1
            self._sensor_layout = struct.Struct("<" + ("h" if s.dtype == "int16" else "i") * width)
            self._sensor_values = [0] * width
            self._sensor_max = 0x7FFF if s.dtype == "int16" else 0x7FFFFFFF
        self.faults: list[Fault] = []
        self.sync_count = 0
        self.sent: list[tuple[int, bytes]] | None = None  # set to a list to record every frame
        self._lock = threading.Lock()
        self.reset_world()
        for d in self.drives:  # power-up: boot-up frame, then PRE-OPERATIONAL
            d.node.nmt.send_command(_NMT_RESET)
            d.node.nmt.send_command(_NMT_PREOP)

    # --- world ---------------------------------------------------------------------------
    def reset_world(self) -> None:
        """A fresh plant at the config's initial pose, joints held until all drives enable."""
        from teleop_rt.hal.sim import make_sim

        self.plant: SimBackend = make_sim(self.cfg, self.side, None, operator=self.operator)
        self.released = False
        self.world_tick = 0
        self.tau = [0.0] * len(self.drives)
        fb = self.plant.read()
        self._q, self._v, self._tau_ext = fb.q_mv, fb.v_mv, fb.tau_mv
        self._outbox: list[tuple[int, bytes]] | None = None
        self._silent: set[int] = set()
        self._lazy = False  # True with asynchronous RPDOs (see _on_sync)

    # --- frames ------------------------------------------------------------------------------
    def send(self, cob_id: int, data: bytes, error_frame: bool = False) -> None:
        if self.sent is not None:
            self.sent.append((cob_id, bytes(data)))
        self.bus.send(
            can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                        is_error_frame=error_frame)
        )  # fmt: skip

    def poll(self) -> None:
        """Handle every frame waiting on the bus (the stepped mode's whole step)."""
        with self._lock:
            recv = self.bus.recv
            while (msg := recv(0.0)) is not None:
                self.handle(msg)

    def handle(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        cob = msg.arbitration_id
        if cob == 0x080:
            self._on_sync()
            return
        data = bytes(msg.data)
        for d in self.drives:
            pdo = d.rpdos.get(cob)
            if pdo is not None:
                if d.nmt_state == "OPERATIONAL":
                    d.on_rpdo(pdo, data)
                return
        if cob == 0x000 and len(data) == 2:
            self.network.notify(cob, bytearray(data), msg.timestamp)  # canopen's NmtSlave
            for d in self.drives:
                if data[1] in (0, d.node_id):
                    d.on_nmt(data[0])
            if data[0] == _NMT_RESET:
                self.reset_world()
            self._outbox = None  # PDOs on or off: the next SYNC samples afresh
            self._lazy = any(p.trans_type >= 254 for d in self.drives for p in d.rpdos.values())
            return
        if 0x701 <= cob <= 0x77F:
            for d in self.drives:
                if d.watch_master_id == cob - 0x700:
                    d.master_seen_us = self.heartbeat_clock_us()
            return
        self.network.notify(cob, bytearray(data), msg.timestamp)  # SDO requests

    def _on_sync(self) -> None:
        """Answer at once with what was prepared for this SYNC, then take the new commands and
        prepare the next answer (so a drive answers SYNC without computing first). With
        asynchronous RPDOs the torque may change during the period: then the plant is advanced
        when the SYNC comes, before answering."""
        self.sync_count += 1
        self.time_us += self.period_us
        now = self.heartbeat_clock_us()
        if self._lazy:  # asynchronous RPDOs acted during the period: advance only now
            self._prepare(advance=True)
        elif self._outbox is None:  # nothing prepared (start, NMT change): sample now
            self._prepare(advance=False)
        for cob, data in self._outbox or ():
            self.send(cob, data)
        for d in self.drives:
            d.heartbeat(now, id(d) in self._silent)
            d.watch_master(now)
        for d in self.drives:
            if d.nmt_state == "OPERATIONAL":
                d.latch()  # the RPDOs received since the last SYNC act from now on
        if not self.released and all(d.state == OE for d in self.drives):
            self.released = True  # brakes off: the world clock starts at this SYNC
        if not self._lazy:
            self._prepare(advance=True)

    def heartbeat_clock_us(self) -> int:
        """The drives' clock for heartbeats: the SYNC count when stepped, the wall in ``serve``."""
        if self._wall_origin is None:
            return self.time_us
        return round((time.monotonic() - self._wall_origin) * 1e6)

    def _prepare(self, advance: bool) -> None:
        """The state at the next SYNC: the plant advanced over the coming period with the torques
        now active, the drives' own transitions, the faults due; sampled and packed."""
        if advance and self.released:
            tau = self.tau
            for j, d in enumerate(self.drives):
                tau[j] = d.units.permille_to_torque_nm(d.active_permille)
            self.plant.write(tau)
            self.world_tick += 1
            fb = self.plant.read()
            self._q, self._v, self._tau_ext = fb.q_mv, fb.v_mv, fb.tau_mv
        if advance:
            for d in self.drives:
                d.advance_state()
        # without advance the world tick stays: its lasting faults still hold (a drive told to
        # stop its heartbeat stays silent over an NMT change), its one-shots have fired
        active = self._active_faults(one_shots=advance)
        for kind, d in active:
            self._fire(kind, [d] if kind != "error_frame" else [])
        dropped = {id(d) for kind, d in active if kind == "drop_tpdo"}
        padded = {id(d) for kind, d in active if kind == "long_tpdo"}
        self._silent = {id(d) for kind, d in active if kind == "stop_heartbeat"}
        out: list[tuple[int, bytes]] = []
        next_us = self.time_us + self.period_us if advance else self.time_us
        for j, d in enumerate(self.drives):
            if d.nmt_state == "OPERATIONAL":
                d.sample(self._q[j], self._v[j])
                if id(d) not in dropped:
                    first = len(out)
                    d.tpdo_frames(next_us, out)
                    if id(d) in padded:
                        out[first:] = _padded(out[first:])
        if self.sensor is not None and not any(k == "drop_sensor" for k, _ in active):
            out.append((self.sensor.cob_id, self._sensor_frame()))
        self._outbox = out

    def _sensor_frame(self) -> bytes:
        vals, top = self._sensor_values, self._sensor_max
        for j, ch in enumerate(self._sensor_channels):
            raw = round((self._tau_ext[j] + self.sensor_offset[j]) / self._sensor_scale[j])
            vals[ch] = max(-top - 1, min(top, raw))
        return self._sensor_layout.pack(*vals)

    # --- faults --------------------------------------------------------------------------------
    def inject(self, fault: Fault) -> None:
        """Schedule ``fault`` (see the module docstring); ``at_tick=None``: the answer to the
        very next SYNC is already affected."""
        if fault.node_id is not None and fault.node_id not in self.by_node:
            raise ValueError(f"no emulated drive with node id {fault.node_id}")
        if fault.at_tick is not None:
            self.faults.append(fault)
            return
        fault = Fault(fault.kind, fault.node_id, self.world_tick, fault.ticks)
        targets = self.drives if fault.node_id is None else [self.by_node[fault.node_id]]
        self._fire(fault.kind, targets)
        if fault.kind in _ONE_SHOT:
            return
        self.faults.append(fault)
        out = self._outbox or []
        if fault.kind == "drop_tpdo":
            cobs = {p.cob_id for d in targets for p in d.tpdos}
            out[:] = [(c, data) for c, data in out if c not in cobs]
        elif fault.kind == "drop_sensor" and self.sensor is not None:
            out[:] = [(c, data) for c, data in out if c != self.sensor.cob_id]
        elif fault.kind == "stop_heartbeat":
            self._silent |= {id(d) for d in targets}
        elif fault.kind == "long_tpdo":
            cobs = {p.cob_id for d in targets for p in d.tpdos}
            out[:] = [_padded([f])[0] if f[0] in cobs else f for f in out]

    def _fire(self, kind: str, targets: list[EmulatedDrive]) -> None:
        for d in targets:
            if kind == "emcy":
                d.fault("injected EMCY", EMCY_OVERCURRENT)
            elif kind == "status_fault":
                d.fault("injected statusword fault", None)
        if kind == "error_frame":  # SocketCAN's layout: controller problem, RX error passive
            self.send(0x004, b"\x00\x10" + bytes(6), error_frame=True)

    def _active_faults(self, one_shots: bool = True) -> list[tuple[str, EmulatedDrive]]:
        """The (kind, drive) pairs of the faults active at the world tick; the one-shots due
        are taken off the list (``one_shots=False``: left out and kept)."""
        if not self.faults:
            return []
        k = self.world_tick
        out: list[tuple[str, EmulatedDrive]] = []
        for f in list(self.faults):
            at = f.at_tick
            assert at is not None  # inject() schedules faults with their tick
            if f.kind in _ONE_SHOT:
                on = one_shots and k == at
            else:
                on = at <= k and (f.ticks is None or k < at + f.ticks)
            if on:
                targets = self.drives if f.node_id is None else [self.by_node[f.node_id]]
                if f.kind == "error_frame":
                    targets = targets[:1]  # one frame on the bus, not one per drive
                out.extend((f.kind, d) for d in targets)
                if f.kind in _ONE_SHOT:
                    self.faults.remove(f)
        return out

    # --- free running ----------------------------------------------------------------------------
    def serve(self, stop: threading.Event, idle_sync_periods: int = 5, poll_s: float = 0.0) -> None:
        """Answer frames until ``stop`` is set; while no SYNC comes the clock follows the wall.

        ``poll_s`` > 0: look at the bus without blocking and sleep ``poll_s`` after each empty
        look, instead of blocking in the bus's ``recv``. A drive is always listening; on a VM,
        an emulator woken by each frame from another CPU answers late far more often."""
        last_wall = time.monotonic()
        with self._lock:  # from here heartbeats run on the wall clock (from the same value)
            self._wall_origin = last_wall - self.heartbeat_clock_us() / 1e6
        last_sync = self.sync_count
        idle_after = idle_sync_periods * self.period_us / 1e6
        recv, sleep = self.bus.recv, time.sleep
        while not stop.is_set():
            if poll_s:
                msg = recv(0.0)
                if msg is None:
                    sleep(poll_s)
            else:
                msg = recv(0.01)
            if msg is None and time.monotonic() - last_wall <= idle_after:
                continue  # nothing came and nothing is due
            with self._lock:
                if msg is not None:
                    self.handle(msg)
                now = time.monotonic()
                if self.sync_count != last_sync:
                    last_sync, last_wall = self.sync_count, now
                elif now - last_wall > idle_after:
                    self.time_us += round((now - last_wall) * 1e6)
                    last_wall = now
                    for d in self.drives:
                        d.advance_state()  # e.g. FAULT REACTION ACTIVE -> FAULT
                        # a drive whose heartbeat is stopped stays silent between SYNCs too
                        d.heartbeat(self.heartbeat_clock_us(), id(d) in self._silent)
                        d.watch_master(self.heartbeat_clock_us())


def _padded(frames: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
    """The frames with one byte more (a CAN frame carries 8 at most)."""
    return [(cob, data + b"\0" if len(data) < 8 else data) for cob, data in frames]


class SteppedBus(can.BusABC):
    """The master's bus for an in-process emulator: every ``send`` also steps the emulator.

    Wraps one python-can bus (``virtual``); after a frame is sent, ``on_send`` (the emulator's
    ``poll``) handles it at once, so the emulator's answers are already queued when the master
    looks for them: deterministic, single-threaded, no wall-clock waits.
    """

    emulator: DriveEmulator  # set by ``emulated_bus``

    def __init__(
        self, inner: can.BusABC, on_send: Callable[[], None], owned: tuple[can.BusABC, ...] = ()
    ) -> None:
        self._inner = inner
        self._on_send = on_send
        self._owned = owned  # further buses to shut down with this one (the emulator's)
        # python-can keeps the channel as given; an inner bus without one has None
        super().__init__(channel=getattr(inner, "channel_id", None))  # type: ignore[arg-type]
        self.channel_info = f"stepped emulator on {inner.channel_info}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        self._on_send()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), True

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()
        for bus in self._owned:
            bus.shutdown()


_channel_serial = iter(range(1, 1 << 62))


def emulated_bus(cfg: SessionConfig, side: str, operator: Load | None = None) -> SteppedBus:
    """A master bus with an in-process emulator of ``side``'s drives behind it.

    The emulator is reachable as ``bus.emulator`` (tests inject faults there).
    """
    channel = f"teleop-rt-emulated-{side}-{next(_channel_serial)}"
    emu_bus = can.Bus(interface="virtual", channel=channel)
    master_bus = can.Bus(interface="virtual", channel=channel)
    emu = DriveEmulator(emu_bus, cfg, side, operator=operator, sensor_offset_nm=0.02)
    bus = SteppedBus(master_bus, emu.poll, owned=(emu_bus,))
    bus.emulator = emu
    return bus
