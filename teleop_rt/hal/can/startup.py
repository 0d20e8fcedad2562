"""Start-up of one robot's CiA 402 drives with the ``canopen`` library, before the loop runs.

Per drive, in this order (all by SDO, expedited, the drive in PRE-OPERATIONAL):

1. NMT reset (node or communication, configurable) and wait for every boot-up frame;
2. check the drive: device type 0x1000 must be a CiA 402 device, 0x6502 must list cyclic
   synchronous torque (bit 9); read the identity 0x1018 and the motor rated torque 0x6076;
3. mode of operation 0x6060 = 10 (cyclic synchronous torque), quick stop option 0x605A,
   communication-loss reaction 0x6007, optionally max torque 0x6072;
4. SYNC: COB-ID 0x1005 = 0x80, communication cycle period 0x1006 = the tick in us;
5. heartbeats: the drive produces every ``heartbeat_ms`` (0x1017) and watches the master's
   heartbeat (0x1016:01 = master node id << 16 | timeout in ms);
6. PDO mapping with canopen's PDO maps (disable, map, set transmission type, enable):
   RPDO1 = controlword 0x6040 + target torque 0x6071 (synchronous), TPDO1 = position 0x6064
   + velocity 0x606C every SYNC, TPDO2 = statusword 0x6041 + torque actual 0x6077 every
   ``status_every_sync`` SYNCs, TPDO3 = digital inputs 0x60FD every SYNC on a drive that
   carries the operator's clutch or presence input (``clutch_input``, ``presence_input``);
   the other PDOs are disabled;

then NMT start for all drives at once. canopen needs its notifier thread for SDO answers; the
caller stops it afterwards and the cyclic loop owns the bus.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import can
import canopen
from canopen import objectdictionary as odt
from canopen.sdo.exceptions import SdoAbortedError, SdoError

from teleop_rt.errors import BackendError
from teleop_rt.hal.can.codec import JointUnits, rated_torque_nm
from teleop_rt.hal.can.config import DEFAULT_EDS, CanSideSpec, CanSpec, DriveSpec

DEVICE_PROFILE_402 = 402
CST_SUPPORTED_BIT = 1 << 9  # 0x6502 bit 9: cyclic synchronous torque
MODE_CST = 10
NOTIFIER_CYCLE_S = 0.02  # canopen's notifier thread wakes this often (stops this fast)


@dataclass(frozen=True)
class DriveInfo:
    """What start-up learned about one drive."""

    node_id: int
    vendor_id: int
    product_code: int
    rated_torque_raw: int  # 0x6076 as read
    units: JointUnits


def object_name(od: odt.ObjectDictionary, index: int, sub: int) -> str:
    """An object's name as the EDS gives it (a record's or array's entry: 'parent: entry')."""
    try:
        obj = od[index]
    except KeyError:
        return "not in the EDS"
    if isinstance(obj, odt.ODVariable):
        return obj.name
    try:
        entry = obj[sub].name
    except KeyError:
        return f"{obj.name}: no subindex {sub} in the EDS"
    return entry if entry.startswith(obj.name) else f"{obj.name}: {entry}"


class Startup:
    """Runs the start-up sequence of one robot's drives on ``bus`` (see the module docstring).

    ``what`` names the robot in error messages ('hsi', 'to'), ``bus_label`` its bus as the
    config gives it (interface and channel; default: python-can's ``channel_info``).
    """

    def __init__(
        self,
        bus: can.BusABC,
        what: str,
        side: CanSideSpec,
        spec: CanSpec,
        dt: float,
        bus_label: str | None = None,
    ):
        self.bus = bus
        self.what = what
        self.bus_label = bus_label or str(bus.channel_info)
        self._sdo_at = ("access", 0, 0)  # the last SDO request: what, index, subindex
        self.side = side
        self.spec = spec
        self.period_us = round(dt * 1e6)
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        self.nodes: list[canopen.RemoteNode] = []

    def run(self) -> list[DriveInfo]:
        """Reset, check and configure every drive, NMT start them; return what was learned."""
        while self.bus.recv(0.0) is not None:  # stale frames (old boot-ups) must not count
            pass
        booted = {d.node_id: threading.Event() for d in self.side.drives}

        def on_bootup(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) == 1 and data[0] == 0:
                booted[can_id - 0x700].set()

        for d in self.side.drives:
            node = canopen.RemoteNode(d.node_id, self._od(d))
            node.sdo.RESPONSE_TIMEOUT = self.spec.sdo_timeout_s
            self._track_sdo(node.sdo)
            self.network.add_node(node)
            self.network.subscribe(0x700 + d.node_id, on_bootup)
            self.nodes.append(node)
        self.network.connect()  # starts canopen's notifier on our bus
        try:
            self._reset(booted)
            pairs = zip(self.nodes, self.side.drives, strict=True)
            infos = [self._configure(node, d) for node, d in pairs]
            for node in self.nodes:
                node.nmt.state = "OPERATIONAL"
        except can.CanError as exc:
            raise BackendError(f"can: {self.what} bus ({self.bus_label}): {exc}") from None
        finally:
            self.stop_notifier()
        return infos

    def stop_notifier(self) -> None:
        notifier = self.network.notifier
        if notifier is not None:
            notifier.stop(1.0)
            self.network.notifier = None

    def _track_sdo(self, sdo: canopen.sdo.SdoClient) -> None:
        """Remember each request's object, so that an abort in the middle of canopen's PDO
        mapping (which does not say which object it wrote) names it."""
        upload, download = sdo.upload, sdo.download

        def tracked_upload(index: int, subindex: int) -> bytes:
            self._sdo_at = ("read", index, subindex)
            return upload(index, subindex)

        def tracked_download(index: int, subindex: int, data: bytes, force_segment=False):
            self._sdo_at = ("write", index, subindex)
            return download(index, subindex, data, force_segment)

        # canopen has no hook for this: the client's own methods are wrapped
        sdo.upload, sdo.download = tracked_upload, tracked_download  # type: ignore[method-assign]

    def _sdo_failed(self, node: canopen.RemoteNode, d: DriveSpec, exc: SdoError, value=None):
        """BackendError naming the drive, the object of the failed request and why."""
        what, index, sub = self._sdo_at
        name = object_name(node.object_dictionary, index, sub)
        to = "" if value is None else f" = {value}"
        how = "aborted by the drive" if isinstance(exc, SdoAbortedError) else "failed"
        return BackendError(
            f"can: {self._drive(d)}: SDO {what} 0x{index:04X}:{sub:02X} ({name}){to} {how}: {exc}"
        )

    # --- steps -------------------------------------------------------------------------------
    def _od(self, d: DriveSpec) -> canopen.ObjectDictionary:
        path = d.eds or DEFAULT_EDS
        try:
            return canopen.import_od(str(path), d.node_id)
        except (OSError, ValueError, KeyError) as exc:
            raise BackendError(
                f"can: {self._drive(d)}: cannot read the EDS {path}: {exc}"
            ) from None

    def _reset(self, booted: dict[int, threading.Event]) -> None:
        mode = self.spec.nmt_reset_at_start
        for node in self.nodes:
            if mode == "none":
                node.nmt.state = "PRE-OPERATIONAL"
            else:
                node.nmt.state = "RESET" if mode == "node" else "RESET COMMUNICATION"
        if mode == "none":
            return
        for d in self.side.drives:
            if not booted[d.node_id].wait(self.spec.boot_timeout_s):
                raise BackendError(
                    f"can: {self._drive(d)}: no boot-up within {self.spec.boot_timeout_s:g} s "
                    f"after NMT reset (is the drive powered and on {self.bus_label}?)"
                )

    def _configure(self, node: canopen.RemoteNode, d: DriveSpec) -> DriveInfo:
        spec = self.spec
        device_type = self._read(node, d, 0x1000)
        if device_type & 0xFFFF != DEVICE_PROFILE_402:
            raise BackendError(
                f"can: {self._drive(d)}: not a CiA 402 drive (device type 0x{device_type:08X})"
            )
        if not self._read(node, d, 0x6502) & CST_SUPPORTED_BIT:
            raise BackendError(
                f"can: {self._drive(d)}: does not support cyclic synchronous torque (0x6502)"
            )
        vendor = self._read(node, d, 0x1018, 1)
        product = self._read(node, d, 0x1018, 2)
        rated_raw = self._read(node, d, 0x6076)
        try:
            units = JointUnits(
                d.counts_per_rev,
                d.gear_ratio,
                rated_torque_nm(rated_raw, d.rated_torque_unit_nm),
                d.direction,
                d.velocity_unit,
            )
        except ValueError as exc:
            raise BackendError(f"can: {self._drive(d)}: {exc}") from None
        self._write(node, d, 0x6060, MODE_CST)
        self._write(node, d, 0x605A, spec.quick_stop_option)
        self._write(node, d, 0x6007, spec.comm_loss_reaction)
        if d.max_torque_permille is not None:
            self._write(node, d, 0x6072, d.max_torque_permille)
        self._write(node, d, 0x1005, 0x80)
        self._write(node, d, 0x1006, self.period_us)
        self._write(node, d, 0x1017, spec.heartbeat_ms)
        self._write(
            node, d, 0x1016, spec.master_node_id << 16 | spec.master_heartbeat_timeout_ms, 1
        )
        self._map_pdos(node, d)
        return DriveInfo(d.node_id, vendor, product, rated_raw, units)

    def _map_pdos(self, node: canopen.RemoteNode, d: DriveSpec) -> None:
        layout = {
            ("rpdo", 1): ([0x6040, 0x6071], 1 if self.spec.rpdo_transmission == "sync" else 255),
            ("tpdo", 1): ([0x6064, 0x606C], 1),
            ("tpdo", 2): ([0x6041, 0x6077], self.spec.status_every_sync),
        }
        if any(x.drive == d.node_id for x in self.side.inputs().values()):
            layout["tpdo", 3] = ([0x60FD], 1)
        try:
            for kind in ("rpdo", "tpdo"):
                maps = getattr(node, kind).map
                for number, pdo in maps.items():
                    if number > 4:
                        break
                    objects, trans = layout.get((kind, number), (None, None))
                    pdo.clear()
                    pdo.cob_id = pdo.predefined_cob_id
                    pdo.enabled = objects is not None
                    pdo.trans_type = trans
                    for index in objects or ():
                        pdo.add_variable(index)
                    pdo.save()
        except SdoError as exc:
            raise self._sdo_failed(node, d, exc) from None
        except (KeyError, ValueError) as exc:  # an object the EDS lacks or cannot map
            raise BackendError(f"can: {self._drive(d)}: PDO mapping failed: {exc}") from None
        for kind, number in layout:
            if number not in getattr(node, kind).map:
                raise BackendError(f"can: {self._drive(d)}: the EDS has no {kind.upper()}{number}")

    def _variable(self, node: canopen.RemoteNode, d: DriveSpec, index: int, sub: int):
        try:
            obj = node.sdo[index]
            return obj[sub] if sub or not isinstance(obj, canopen.sdo.SdoVariable) else obj
        except KeyError:
            name = object_name(node.object_dictionary, index, sub)
            eds = d.eds or DEFAULT_EDS
            raise BackendError(
                f"can: {self._drive(d)}: object 0x{index:04X}:{sub:02X} ({name}): not in the "
                f"EDS {eds}"
            ) from None

    def _read(self, node: canopen.RemoteNode, d: DriveSpec, index: int, sub: int = 0) -> int:
        var = self._variable(node, d, index, sub)
        try:
            return int(var.raw)
        except SdoError as exc:
            raise self._sdo_failed(node, d, exc) from None

    def _write(self, node: canopen.RemoteNode, d: DriveSpec, index: int, value: int, sub: int = 0):
        var = self._variable(node, d, index, sub)
        try:
            var.raw = value
        except SdoError as exc:
            raise self._sdo_failed(node, d, exc, value) from None
        except ValueError as exc:  # the value does not fit the EDS's data type
            name = object_name(node.object_dictionary, index, sub)
            raise BackendError(
                f"can: {self._drive(d)}: SDO write 0x{index:04X}:{sub:02X} ({name}) = {value}: "
                f"{exc}"
            ) from None

    def _drive(self, d: DriveSpec) -> str:
        return f"{self.what} drive node {d.node_id}"
