"""The CAN backend: one robot's CiA 402 drives in cyclic synchronous torque mode over python-can.

Its lifecycle (``teleop_rt.hal.base``, as ros2_control's): ``configure()`` opens the robot's
bus and runs the canopen start-up (``startup.Startup``: NMT reset, drive check, SDO
configuration, PDO mapping, NMT start); ``activate()`` cycles SYNC while the robot rests with
its drives disabled to zero the external-torque sensor, and steps the CiA 402 state machine to
OPERATION ENABLED. From then on the loop owns the bus; per tick:

* ``read()``: handle the frames that came in since the last window (late TPDOs, EMCY,
  heartbeats), send SYNC, collect TPDO1 of every drive (position, velocity), TPDO2 where it is
  due (statusword, torque actual) and the torque sensor's TPDO until all are in or the window
  (``feedback_window_us`` after SYNC) closes; step each drive's CiA 402 stepper with its
  latest statusword; check for faults; convert to joint SI units;
* ``write(tau)``: one RPDO per drive with the stepper's controlword and the target torque
  (zero unless the drive reports OPERATION ENABLED), and the master's heartbeat when due.

Frames are packed and unpacked with the precompiled structs of ``codec`` into preallocated
messages (canopen's PDO objects cost about 15 us per access).

Faults end the session with ``SafetyStop`` from ``read()`` or ``write()``, naming the robot,
joint, drive node and reason: a drive's feedback missing ``missed_feedback_ticks`` (3) ticks in
a row, an EMCY, a drive heartbeat not seen for ``heartbeat_timeout_ms`` (wall clock, like the
master's heartbeat every ``master_heartbeat_ms``: not counted in ticks), a statusword that
leaves OPERATION ENABLED (fault, quick stop, disabled), a drive leaving NMT OPERATIONAL, a CAN
error frame (seen in the frames the cycle reads anyway), a bus the interface reports in
``BusState.ERROR`` (polled every ``missed_feedback_ticks`` ticks: a counter check per tick, the
interface call only then) or a failing send / receive. The stop then sends zero torque with
quick stop until each drive reports SWITCH ON DISABLED (disable voltage for those that did not
get there within ``stop_ticks``), then NMT pre-operational, and the bus is closed: the
deactivation, stepped one SYNC period per ``deactivate_step`` (``begin_deactivate`` first), so
that ``teleop_rt.hal.stopping.stop_all`` stops both robots together, each bus cycling every
period until its drives are disabled; ``deactivate()`` / ``shutdown()`` run it to the end here.
A CAN backend runs once: a second ``configure`` or ``activate`` after its activation raises
``LifecycleError`` (its drives were stopped; a new start-up is a new backend).

Between a robot's activation and the loop's first ``read`` (while the session starts the other
robot), a keepalive thread runs the same cycle with zero torque, so the drives keep their SYNC
and the master's heartbeat (their 0x1016 watch) and faults are still checked.

Transport: the torque sent after the feedback of SYNC k takes effect at SYNC k+1 (synchronous
RPDO), one tick later than on the simulated backend, whose ``write`` acts on the state it read.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from teleop_rt.errors import BackendError, ConfigError, SafetyStop
from teleop_rt.hal.base import Backend, LifecycleError
from teleop_rt.hal.can import codec
from teleop_rt.hal.can.config import CanSpec
from teleop_rt.hal.signals import INPUT_CLUTCH, INPUT_PRESENT, Feedback

if TYPE_CHECKING:
    import threading

    import can

    from teleop_rt.config import SessionConfig
    from teleop_rt.hal.can.emulator import DriveEmulator
    from teleop_rt.model import RobotModel
    from teleop_rt.world import Load

_TPDO1, _TPDO2, _EMCY, _HEARTBEAT, _SENSOR, _TPDO3 = range(6)
_TPDO1_SIZE, _TPDO2_SIZE = codec.TPDO1_STRUCT.size, codec.TPDO2_STRUCT.size
_unpack_tpdo1, _unpack_tpdo2 = codec.TPDO1_STRUCT.unpack_from, codec.TPDO2_STRUCT.unpack_from
_TPDO3_SIZE, _unpack_tpdo3 = codec.TPDO3_STRUCT.size, codec.TPDO3_STRUCT.unpack_from
_SOD = "SWITCH ON DISABLED"
# the stop's phases
_QUICK_STOP, _DISABLE, _NMT, _DONE = "quick stop", "disable", "NMT pre-operational", "done"
_FAULT_STATES = ("FAULT", "FAULT REACTION ACTIVE")


class CanBackend(Backend):
    """One robot on one CAN bus (see the module docstring).

    Parameters:
        cfg: the session config; its ``can`` section (defaults if absent) and ``rate_hz``.
        side: 'hsi' or 'to'.
        n: the robot's number of joints (one drive each).
        operator: passed to an in-process emulator (``can.emulate``) like to the sim backend.
    """

    def __init__(
        self, cfg: SessionConfig, side: str, n: int, operator: Load | None = None
    ) -> None:
        super().__init__(n, len(cfg.environment) if side == "to" else 0)
        spec = cfg.can if cfg.can is not None else CanSpec()
        side_spec = spec.side(side)
        key = f"can.{side}"
        if len(side_spec.drives) != n:
            raise ConfigError(
                f"{key}.drives: {len(side_spec.drives)} drive(s) but the robot has {n} joints"
            )
        side_spec.check_eds(key)  # a missing EDS is the config's fault: said before any bus opens
        sensor = side_spec.torque_sensor
        if sensor is not None:
            scale = sensor.scale_nm if isinstance(sensor.scale_nm, list) else [sensor.scale_nm] * n
            channels = sensor.channels if sensor.channels is not None else list(range(n))
            if len(scale) != n or len(channels) != n:
                raise ConfigError(f"{key}.torque_sensor: needs one scale / channel per joint ({n})")
            width = max(channels) + 1
            if width * (2 if sensor.dtype == "int16" else 4) > 8:
                raise ConfigError(f"{key}.torque_sensor: {width} {sensor.dtype} exceed 8 bytes")
            import struct

            code = "h" if sensor.dtype == "int16" else "i"
            self._sensor_layout = struct.Struct("<" + code * width)
            self._sensor_scale = [float(s) for s in scale]
            self._sensor_channels = channels
        self.cfg = cfg
        self.spec = spec
        self.side = side
        self.side_spec = side_spec
        self.operator = operator
        self.sensor = sensor
        self.node_ids = [d.node_id for d in side_spec.drives]
        self.emulator: DriveEmulator | None = None  # the in-process emulator (can.emulate)
        self.bus: can.BusABC | None = None
        self.can_tap = None  # every frame to this (--can-log: canlog.CanLog.tap) if set
        self.drive_info: list = []
        self.period_ns = round(cfg.dt * 1e9)
        self.window_ns = 0 if spec.emulate else spec.feedback_window_us * 1000
        # Heartbeats are wall-clock times on both sides (a drive's 0x1016 watch runs on its own
        # clock), whatever the tick rate: ticks run faster than real time in fast mode, and a
        # loaded host stretches them. The in-process emulator's clock is the tick, so there
        # ``_now`` is too (deterministic tests).
        self._now = self._tick_time if spec.emulate else time.perf_counter_ns
        self.hb_timeout_ns = spec.heartbeat_timeout_ms * 1_000_000  # a drive's heartbeat lost
        self.master_hb_ns = spec.master_heartbeat_ms * 1_000_000  # the master's, this often
        self.status_every = spec.status_every_sync
        self.missed_limit = spec.missed_feedback_ticks
        # per drive, raw feedback and state
        self._pos = [0] * n
        self._vel = [0] * n
        self._sw = [0] * n
        self._torque_actual = [0] * n
        self._cw = [0] * n
        self._miss = [0] * n
        self._last_hb_ns = [0] * n  # when each drive's heartbeat last came (``_now``)
        self._hb_operational = [False] * n  # a drive's heartbeat said OPERATIONAL once
        self._next_status = [0] * n
        self._rad_per_count = [0.0] * n
        self._rad_s_per_unit = [0.0] * n
        self._offset = [d.zero_offset_rad for d in side_spec.drives]
        self._units: list[codec.JointUnits] = []
        self._steppers: list = []
        self._sensor_raw: list[int] = [0] * (width if sensor is not None else 0)
        # the operator's inputs (0x60FD in TPDO3 every SYNC): the drives carrying one, their
        # raw inputs, and (drive index, bit mask) of the clutch / presence bit (-1: none)
        where = {d.node_id: j for j, d in enumerate(side_spec.drives)}
        inputs = side_spec.inputs()
        self._input_drives = sorted({where[x.drive] for x in inputs.values()})
        self._di = [0] * n
        self._clutch, self._presence = (
            (where[x.drive], 1 << x.bit) if x is not None else (-1, 0)
            for x in (side_spec.clutch_input, side_spec.presence_input)
        )
        self._sensor_zero = [0.0] * n
        self._sensor_miss = 0
        self._routes: dict[int, tuple[int, int]] = {}
        self._faults: list[str] = []
        self._got = 0
        self.tick = 0
        self.master_hb_at_ns = -(1 << 62)  # the master's last heartbeat (``_now``; first: at once)
        self.running = False  # the session's ticks (after start-up)
        self._cyclic = False  # drives are NMT operational and the loop owns the bus
        self._stop_phase: str | None = None  # None, then _QUICK_STOP, ..., _DONE
        self._started: tuple[list, can.BusABC] | None = None  # configure_started's
        self._ran = False  # activated once: a CAN backend runs once
        self._stop_count = 0  # periods spent in the stop phase
        self._faulted = False
        self._keepalive: tuple[threading.Event, threading.Thread] | None = None
        self._keepalive_fault: str | None = None  # the first fault the keepalive saw
        self._next_state_poll = 0  # tick of the next bus.state poll
        self._bus_name = f"can: {side} bus"
        self.stats = {
            "ticks": 0, "missed_windows": 0, "late_frames": 0, "saturated": 0, "bus_warnings": 0,
            "long_pdos": 0,
        }  # fmt: skip
        self._long_pdos: dict[int, list[int]] = {}  # COB-ID: [count, length, mapped length]
        self.last_bus_warning: str | None = None  # the last warning error frame, described
        self.stop_report: list[str] = []

    # --- lifecycle (teleop_rt.hal.base) ------------------------------------------------------
    def on_configure(self) -> None:
        """Open the bus and run the canopen start-up (``startup.Startup``): the drives checked,
        configured, mapped and NMT operational. A start-up that fails closes the bus."""
        from teleop_rt.hal.can.startup import Startup

        self._refuse_a_second_run("configure")
        if self._started is not None:  # configure_started: drives started elsewhere
            self.drive_info, self.bus = self._started
            return
        bus = self._open_bus()
        try:
            startup = Startup(
                bus, self.side, self.side_spec, self.spec, self.cfg.dt, self._bus_label()
            )
            self.drive_info = startup.run()
        except BaseException:
            self._close_bus()
            raise

    def configure_started(self, info: list, bus: can.BusABC) -> None:
        """``configure`` for drives already configured and NMT operational on ``bus`` (``info``
        as ``Startup.run`` returns it): tools measuring the backend without a transport."""
        self._started = (info, bus)
        self.configure()

    def on_activate(self) -> None:
        """Zero the torque sensor (drives disabled, robot at rest), enable the drives (CiA 402
        to OPERATION ENABLED), and keep the cycle going until the loop's first ``read``."""
        self._refuse_a_second_run("activate")
        self._ran = True
        self._begin_cyclic(self.drive_info)
        if not self.spec.emulate:
            self._start_keepalive()

    def _refuse_a_second_run(self, transition: str) -> None:
        # once deactivated the drives are NMT pre-operational and the bus is closed; starting
        # them again is a new start-up with fresh state: a new backend
        if self._ran:
            raise LifecycleError(
                f"CanBackend ({self.side}): cannot {transition} a second time (its drives ran "
                "once and were stopped; build a new backend)"
            )

    def _begin_cyclic(self, info: list) -> None:
        """The cyclic part of activation (``info`` as ``Startup.run`` returns it): zero the
        sensor, enable."""
        import can

        from teleop_rt.hal.can.cia402 import Cia402Stepper

        self.drive_info = info
        self._units = [d.units for d in info]
        for i, u in enumerate(self._units):
            self._rad_per_count[i] = u.counts_to_rad(1)
            self._rad_s_per_unit[i] = u.velocity_to_rad_s(1)
        self._steppers = [Cia402Stepper() for _ in info]
        self._build_routes()
        self._prepare_messages(can)
        self._last_hb_ns[:] = [self._now()] * self.n  # the watch starts now
        self._cyclic = True
        try:
            self._zero_sensor()
            self._enable()
        except SafetyStop:
            self._latch_fault()
            raise
        self.running = True

    def _start_keepalive(self) -> None:
        """Until the loop's first ``read``, a thread keeps the cycle going (SYNC, zero torque,
        the master's heartbeat): the drives watch the master's heartbeat (0x1016) and expect
        SYNC, and the session starts the other robot's drives in between (seconds with SDO
        and sensor zeroing). The first fault it sees quick-stops this robot's drives (never a
        fault reset and re-enable behind the session's back) and is raised by ``read``; SYNC
        and heartbeat go on unless the bus itself failed."""
        import threading

        stop = threading.Event()
        name = f"can-{self.side}-keepalive"
        thread = threading.Thread(target=self._keepalive_loop, args=(stop,), name=name, daemon=True)
        self._keepalive = (stop, thread)
        thread.start()

    def _keepalive_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self._pace()
            try:
                self._cycle()
                self._step_steppers()
                if self._keepalive_fault is None:
                    self._keepalive_check()
                self._faults.clear()
                self._send_commands(None)
            except SafetyStop as exc:  # the bus failed: nothing more to send
                self._keepalive_fault = self._keepalive_fault or str(exc)
                return

    def _keepalive_check(self) -> None:
        try:
            self._check(running=True)
        except SafetyStop as exc:
            self._keepalive_fault = str(exc)
            for st in self._steppers:
                st.request_stop()
            self._step_steppers()  # this tick's controlwords already quick-stop

    def _step_steppers(self) -> None:
        steppers, sw, cw = self._steppers, self._sw, self._cw
        for i in range(self.n):
            cw[i] = steppers[i].step(sw[i])

    def _end_keepalive(self) -> None:
        """The loop's first ``read``: the keepalive stops; a fault it saw is raised now."""
        self._join_keepalive()
        fault, self._keepalive_fault = self._keepalive_fault, None
        if fault is not None:
            self._latch_fault()
            raise SafetyStop(fault)

    def _join_keepalive(self) -> None:
        if self._keepalive is not None:
            stop, thread = self._keepalive
            stop.set()
            thread.join()
            self._keepalive = None

    def _open_bus(self) -> can.BusABC:
        if self.bus is not None:
            return self.bus
        if self.spec.emulate:
            from teleop_rt.hal.can.emulator import emulated_bus

            stepped = emulated_bus(self.cfg, self.side, self.operator)
            self.emulator = stepped.emulator
            bus: can.BusABC = stepped
        else:
            import can

            kwargs = self.side_spec.bus.kwargs()
            try:
                bus = can.Bus(**kwargs)
            except (can.CanError, ImportError, OSError, ValueError, TypeError) as exc:
                described = ", ".join(f"{k}={v}" for k, v in kwargs.items())
                raise BackendError(
                    f"can: {self.side} bus ({described}): cannot open: {exc}"
                ) from None
        if self.can_tap is not None:  # from here on, start-up included, every frame is logged
            from teleop_rt.hal.can.canlog import TappedBus

            bus = TappedBus(bus, self.can_tap)
        self.bus = bus
        return bus

    def _bus_label(self) -> str:
        """The bus as the user knows it: interface and channel (the emulator's own name)."""
        if self.spec.emulate or self.bus is None:
            return str(getattr(self.bus, "channel_info", "?"))
        b = self.side_spec.bus
        return b.interface if b.channel is None else f"{b.interface} {b.channel}"

    def _build_routes(self) -> None:
        r = self._routes
        for i, node in enumerate(self.node_ids):
            r[codec.tpdo1_cob_id(node)] = (_TPDO1, i)
            r[codec.tpdo2_cob_id(node)] = (_TPDO2, i)
            r[codec.emcy_cob_id(node)] = (_EMCY, i)
            r[codec.heartbeat_cob_id(node)] = (_HEARTBEAT, i)
        for i in self._input_drives:
            r[codec.tpdo3_cob_id(self.node_ids[i])] = (_TPDO3, i)
        if self.sensor is not None:
            r[self.sensor.cob_id] = (_SENSOR, 0)

    def _prepare_messages(self, can) -> None:
        self._sync_msg = can.Message(
            arbitration_id=codec.COB_ID_SYNC, is_extended_id=False, data=b""
        )
        self._rpdo_msgs = [
            can.Message(
                arbitration_id=codec.rpdo1_cob_id(node), is_extended_id=False, data=bytearray(4)
            )
            for node in self.node_ids
        ]
        master = self.spec.master_node_id
        self._hb_msg = can.Message(
            arbitration_id=0x700 + master, is_extended_id=False, data=b"\x05"
        )
        self._nmt_msg = can.Message(
            arbitration_id=codec.COB_ID_NMT, is_extended_id=False, data=bytearray(2)
        )
        self._can_error = can.CanError
        self._bus_error_state = can.BusState.ERROR
        self._bus_name = f"can: {self.side} bus ({self._bus_label()})"
        self._next_state_poll = self.tick + 1
        bus = self.bus
        assert bus is not None  # activation follows configure's bus
        self._recv = bus.recv
        self._send_raw = bus.send
        self._next_ns = time.perf_counter_ns()

    def _tick_time(self) -> int:
        """The in-process emulator's clock: the ticks so far, in ns."""
        return self.tick * self.period_ns

    def _pace(self) -> None:
        """Start-up and stop run at the real SYNC period (a drive expects it); not emulated."""
        if self.spec.emulate:
            return
        self._next_ns += self.period_ns
        delay = self._next_ns - time.perf_counter_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
        else:
            self._next_ns = time.perf_counter_ns()

    def _zero_sensor(self) -> None:
        """Drives disabled (faults reset), robot at rest: average the sensor for the offset."""
        sensor = self.sensor
        ticks = sensor.zero_ticks if sensor is not None else 0
        sums = [0.0] * len(self._sensor_raw)
        count = 0
        bit = 1 << (2 * self.n)
        for _ in range(max(ticks, 1)):
            self._pace()
            self._cycle()
            self._check(running=False)
            for i, st in enumerate(self._steppers):
                cw = st.step(self._sw[i])
                self._cw[i] = cw if st.state == "FAULT" else 0x00
            if sensor is not None and self._got & bit:
                count += 1
                for c, x in enumerate(self._sensor_raw):
                    sums[c] += x
            self._send_commands(None)
        if sensor is not None and ticks:
            if not count:
                raise SafetyStop(f"can: {self.side} torque sensor 0x{sensor.cob_id:03X}: no data")
            for j, c in enumerate(self._sensor_channels):
                self._sensor_zero[j] = sums[c] / count

    def _enable(self) -> None:
        limit = self.spec.enable_timeout_ticks
        for _ in range(limit):
            self._pace()
            self._cycle()
            self._check(running=False)
            done = True
            for i, st in enumerate(self._steppers):
                self._cw[i] = st.step(self._sw[i])
                done = done and st.state == "OPERATION ENABLED"
            if done:
                self._fill_feedback()
                return
            self._send_commands(None)
        states = ", ".join(
            f"node {node}: {st.state}"
            for node, st in zip(self.node_ids, self._steppers, strict=True)
        )
        raise SafetyStop(
            f"can: {self.side} drives did not reach OPERATION ENABLED within {limit} ticks "
            f"({states})"
        )

    # --- the cyclic exchange -------------------------------------------------------------------
    def _cycle(self) -> None:
        """Drain, SYNC, collect until everything expected is in or the window closes."""
        self.tick += 1
        tick = self.tick
        recv, on_frame = self._recv, self._on_frame
        try:
            while (msg := recv(0.0)) is not None:  # late frames of the last window, EMCY, ...
                on_frame(msg, False)
            if tick >= self._next_state_poll:
                self._poll_bus_state()
            self._send_raw(self._sync_msg)
            n = self.n
            expected = (1 << n) - 1
            for i in range(n):
                if tick >= self._next_status[i]:
                    expected |= 1 << (n + i)
            if self.sensor is not None:
                expected |= 1 << (2 * n)
            for i in self._input_drives:
                expected |= 1 << (2 * n + 1 + i)
            self._got = 0
            deadline = time.perf_counter_ns() + self.window_ns
            while self._got & expected != expected:
                remaining = deadline - time.perf_counter_ns()
                msg = recv(remaining / 1e9 if remaining > 0 else 0.0)
                if msg is None:
                    break
                on_frame(msg, True)
        except self._can_error as exc:
            raise SafetyStop(f"{self._bus_name}: bus error: {exc}") from None
        got = self._got
        missed = False
        for i in range(self.n):
            status, inputs = 1 << (n + i), 1 << (2 * n + 1 + i)
            if (got & (1 << i) and (got & status or not expected & status)
                    and (got & inputs or not expected & inputs)):  # fmt: skip
                self._miss[i] = 0
            else:
                self._miss[i] += 1
                missed = True
        if self.sensor is not None:
            if got & (1 << (2 * n)):
                self._sensor_miss = 0
            else:
                self._sensor_miss += 1
                missed = True
        fb = self.feedback
        if missed:
            self.stats["missed_windows"] += 1
            fb.age_ticks += 1
        else:
            fb.age_ticks = 0

    def _poll_bus_state(self) -> None:
        """The interface's view of the bus (those without one say ACTIVE): ERROR is bus off or
        a bus coupling error. Polled every ``missed_feedback_ticks`` ticks: no later than the
        missing feedback a dead bus causes, and with the reason; some interfaces pay a driver
        call for it. PASSIVE is not a fault: it means listen-only on some interfaces."""
        self._next_state_poll = self.tick + self.missed_limit
        if self.bus.state is self._bus_error_state:  # type: ignore[union-attr]  # cyclic: open
            self._faults.append(f"{self._bus_name}: bus state ERROR (bus off or coupling error)")

    def _on_frame(self, msg: can.Message, fresh: bool) -> None:
        if msg.is_error_frame:
            what = codec.describe_error_frame(msg.arbitration_id, msg.data)
            if codec.error_frame_is_fault(msg.arbitration_id, msg.data):
                self._faults.append(f"{self._bus_name}: {what}")
            else:  # a warning (lost arbitration, error warning level): counted, not a stop
                self.stats["bus_warnings"] += 1
                self.last_bus_warning = what
            return
        route = self._routes.get(msg.arbitration_id)
        if route is None:
            return  # our own frames (echoed by some interfaces), SDO, other nodes
        kind, i = route
        data = msg.data
        try:
            if kind == _TPDO1:
                if len(data) != _TPDO1_SIZE:  # shorter: a fault; longer: its leading bytes
                    self._long_pdo(msg, codec.TPDO1_NAME, _TPDO1_SIZE)
                self._pos[i], self._vel[i] = _unpack_tpdo1(data)
                if fresh:
                    self._got |= 1 << i
                else:
                    self.stats["late_frames"] += 1
            elif kind == _TPDO2:
                if len(data) != _TPDO2_SIZE:
                    self._long_pdo(msg, codec.TPDO2_NAME, _TPDO2_SIZE)
                self._sw[i], self._torque_actual[i] = _unpack_tpdo2(data)
                if fresh:
                    self._got |= 1 << (self.n + i)
                self._next_status[i] = self.tick + self.status_every
            elif kind == _TPDO3:
                if len(data) != _TPDO3_SIZE:
                    self._long_pdo(msg, codec.TPDO3_NAME, _TPDO3_SIZE)
                (self._di[i],) = _unpack_tpdo3(data)
                if fresh:
                    self._got |= 1 << (2 * self.n + 1 + i)
            elif kind == _SENSOR:
                layout = self._sensor_layout
                if len(data) != layout.size:
                    self._long_pdo(msg, "torque sensor TPDO", layout.size)
                raw = layout.unpack_from(data)
                self._sensor_raw[:] = raw
                if fresh:
                    self._got |= 1 << (2 * self.n)
            elif kind == _EMCY:
                emcy = codec.decode_emcy(data)
                if not emcy.is_reset:
                    self._faults.append(f"{self._drive(i)}: {emcy.describe()}")
            else:
                self._last_hb_ns[i] = self._now()
                state = codec.decode_heartbeat(data)
                if state == "OPERATIONAL":
                    self._hb_operational[i] = True
                elif state == "BOOT-UP" or self._hb_operational[i]:
                    what = "rebooted (boot-up)" if state == "BOOT-UP" else f"NMT state {state}"
                    self._faults.append(f"{self._drive(i)}: {what}")
        except (codec.CanFrameError, ValueError) as exc:
            name = "torque sensor" if kind == _SENSOR else self._drive(i)
            self._faults.append(f"{name}: malformed frame 0x{msg.arbitration_id:03X}: {exc}")

    def _long_pdo(self, msg: can.Message, name: str, mapped: int) -> None:
        """A PDO of another length than its mapping: ``CanFrameError`` if shorter; if longer,
        CiA 301 has the consumer use the mapped leading bytes: counted per COB-ID (notes)."""
        codec.pdo_excess(name, mapped, msg.data)
        self.stats["long_pdos"] += 1
        seen = self._long_pdos.get(msg.arbitration_id)
        if seen is None:
            self._long_pdos[msg.arbitration_id] = [1, len(msg.data), mapped]
        else:
            seen[0] += 1

    def _check(self, running: bool) -> None:
        """Raise SafetyStop for every fault seen this tick (several are joined)."""
        faults = self._faults
        now = self._now()
        for i in range(self.n):
            if self._miss[i] >= self.missed_limit:
                faults.append(
                    f"{self._drive(i)}: no feedback (TPDO) for {self._miss[i]} ticks in a row"
                )
            if now - self._last_hb_ns[i] > self.hb_timeout_ns:
                faults.append(
                    f"{self._drive(i)}: heartbeat lost (none for "
                    f"{(now - self._last_hb_ns[i]) / 1e6:.0f} ms, timeout "
                    f"{self.spec.heartbeat_timeout_ms} ms)"
                )
            if running:
                state = self._steppers[i].state
                if state != "OPERATION ENABLED":
                    why = "drive fault" if state in _FAULT_STATES else "left OPERATION ENABLED"
                    faults.append(
                        f"{self._drive(i)}: {why} (statusword 0x{self._sw[i]:04X}: {state})"
                    )
        if self.sensor is not None and self._sensor_miss >= self.missed_limit:
            faults.append(
                f"can: {self.side} torque sensor 0x{self.sensor.cob_id:03X}: no data for "
                f"{self._sensor_miss} ticks in a row"
            )
        if faults:
            message = "; ".join(dict.fromkeys(faults))
            faults.clear()
            raise SafetyStop(message)

    def _drive(self, i: int) -> str:
        return f"can: {self.side} joint {i} (drive node {self.node_ids[i]})"

    def _send_commands(self, tau) -> None:
        """One RPDO per drive: the controlword and the target torque (zero unless enabled)."""
        steppers, pack, send = self._steppers, codec.RPDO1_STRUCT.pack_into, self._send_raw
        try:
            for i, msg in enumerate(self._rpdo_msgs):
                permille = 0
                if tau is not None and steppers[i].torque_allowed:
                    permille, saturated = self._units[i].torque_nm_to_permille(tau[i])
                    if saturated:
                        self.stats["saturated"] += 1
                pack(msg.data, 0, self._cw[i], permille)
                send(msg)
            now = self._now()
            if now - self.master_hb_at_ns >= self.master_hb_ns:
                send(self._hb_msg)
                self.master_hb_at_ns = now
        except self._can_error as exc:
            raise SafetyStop(f"{self._bus_name}: bus error: {exc}") from None
        except ValueError as exc:  # a NaN torque: never reaches a drive as a number
            raise SafetyStop(f"can: {self.side}: {exc}") from None

    def _fill_feedback(self) -> None:
        fb = self.feedback
        ql, vl, pos, vel = fb.q_mv, fb.v_mv, self._pos, self._vel
        kq, kv, off = self._rad_per_count, self._rad_s_per_unit, self._offset
        for i in range(self.n):
            ql[i] = pos[i] * kq[i] + off[i]
            vl[i] = vel[i] * kv[i]
        if self.sensor is not None:
            raw, zero, scale, te = (
                self._sensor_raw,
                self._sensor_zero,
                self._sensor_scale,
                fb.tau_mv,
            )
            for j, c in enumerate(self._sensor_channels):
                te[j] = (raw[c] - zero[j]) * scale[j]
        (ci, cb), (pi, pb), di = self._clutch, self._presence, self._di
        fb.inputs = (INPUT_CLUTCH if ci >= 0 and di[ci] & cb else 0) | (
            INPUT_PRESENT if pi >= 0 and di[pi] & pb else 0)  # fmt: skip
        emu = self.emulator
        if emu is not None:  # an emulated world: log what it knows, like the sim backend
            w, ew = self.world, emu.plant.world
            w.reference[:] = ew.reference
            w.reference_velocity[:] = ew.reference_velocity
            w.force[:] = ew.force
            w.contacts[:] = ew.contacts

    # --- Backend ----------------------------------------------------------------------------------
    def read(self) -> Feedback:
        fb = self.feedback
        if not self._cyclic or self.bus is None:  # not started (or stopped): nothing measured
            fb.age_ticks = max(fb.age_ticks + 1, self.missed_limit)
            return fb
        if self._keepalive is not None:
            self._end_keepalive()
        try:
            self._cycle()
        except SafetyStop:
            if self._faulted:  # after the stop: report the sensors unusable, never raise twice
                fb.age_ticks += 1
                return fb
            self._latch_fault()
            raise
        steppers, sw, cw = self._steppers, self._sw, self._cw
        for i in range(self.n):
            cw[i] = steppers[i].step(sw[i])
        if self._faulted:
            self._faults.clear()
            self._fill_feedback()
            fb.age_ticks = max(fb.age_ticks, self.missed_limit)
            return fb
        try:
            self._check(running=True)
        except SafetyStop:
            self._latch_fault()
            raise
        self._fill_feedback()
        self.stats["ticks"] += 1
        return fb

    def write(self, tau) -> None:
        if not self._cyclic or self.bus is None:
            return
        try:
            self._send_commands(None if self._faulted else tau)
        except SafetyStop:
            if not self._faulted:
                self._latch_fault()
                raise

    def _latch_fault(self) -> None:
        """This robot raised its SafetyStop: from now on zero torque with quick stop, and
        ``read`` reports the feedback unusable (``age_ticks``) instead of raising again, so a
        session's staged stop ends at once with zero torque; ``stop`` then disables."""
        self._faulted = True
        for st in self._steppers:
            st.request_stop()
        self.feedback.age_ticks = max(self.feedback.age_ticks, self.missed_limit)

    def on_begin_deactivate(self) -> None:
        self.running = False
        self._join_keepalive()
        if self.bus is None or not self._cyclic:  # never cycled: nothing to walk through
            self._stop_phase = _DONE
            self._close_bus()
            return
        for st in self._steppers:
            st.request_stop()
        self._stop_phase, self._stop_count = _QUICK_STOP, 0
        self._next_ns = time.perf_counter_ns()  # ``deactivate`` paces from here

    def on_deactivate_step(self) -> bool:
        """One SYNC period of the stop, zero torque throughout: quick stop until every drive
        reports SWITCH ON DISABLED (or FAULT, or is silent), for at most ``stop_ticks``
        periods; if some did not get there, disable voltage (0x00) until they do, for at most
        ``disable_ticks``; then one last SYNC (the last synchronous RPDO takes effect) and NMT
        pre-operational, and the bus is closed. A drive that did not end in SWITCH ON
        DISABLED is named in ``stop_report``, as is anything else that went wrong: this never
        raises. At most ``stop_ticks + disable_ticks + 1`` calls."""
        if self._stop_phase == _DONE:
            return True
        try:
            if self._stop_phase != _NMT:
                self._stop_cycle_step(self._stop_phase == _DISABLE)
                return False
            self._stop_nmt_step()
        except BaseException:  # a bug, or Ctrl-C: the bus is closed all the same
            self._stop_phase = _DONE
            self._close_bus()
            raise
        return True

    def wait_period(self) -> None:
        self._pace()

    def on_cleanup(self) -> None:
        self.on_shutdown()

    def on_shutdown(self) -> None:
        """The keepalive ended and the bus closed (after a deactivation they already are)."""
        self.running = False
        self._join_keepalive()
        self._close_bus()

    def _stop_nmt_step(self) -> None:
        try:
            self._send_raw(self._sync_msg)
            data = self._nmt_msg.data
            for node in self.node_ids:
                data[0], data[1] = 0x80, node  # enter PRE-OPERATIONAL: PDOs off
                self._send_raw(self._nmt_msg)
        except self._can_error as exc:
            self.stop_report.append(f"{self._bus_name}: bus error at stop: {exc}")
        self._report_drive_states()
        self._stop_phase = _DONE
        self._close_bus()

    def _stop_cycle_step(self, disable: bool) -> None:
        """A quick-stop (or, ``disable``, a disable-voltage) period: SYNC, feedback, RPDOs."""
        self._stop_count += 1
        try:
            self._cycle()
        except SafetyStop as exc:
            self.stop_report.append(str(exc))
            self._stop_phase = _NMT
            return
        self._faults.clear()
        pending = []
        for i, st in enumerate(self._steppers):
            cw = st.step(self._sw[i])  # quick stop until SWITCH ON DISABLED, then 0x00
            silent = self._miss[i] >= self.missed_limit
            self._cw[i] = 0x00 if disable or silent else cw
            if not (silent or st.state in (_SOD, "FAULT")):
                pending.append(f"node {self.node_ids[i]}: {st.state}")
        try:
            self._send_commands(None)
        except SafetyStop as exc:
            self.stop_report.append(str(exc))
            pending = []
        if not pending:
            self._stop_phase = _NMT
        elif not disable and self._stop_count >= self.spec.stop_ticks:
            self.stop_report.append(
                f"can: {self.side}: quick stop not complete after {self._stop_count} ticks "
                f"({', '.join(pending)}): disable voltage sent"
            )
            self._stop_phase, self._stop_count = _DISABLE, 0
        elif disable and self._stop_count >= self.spec.disable_ticks:
            self._stop_phase = _NMT

    def _report_drive_states(self) -> None:
        """Name every drive that is not in SWITCH ON DISABLED as NMT pre-operational goes out."""
        for i, st in enumerate(self._steppers):
            if self._miss[i] >= self.missed_limit:
                what = "no feedback, its state unknown"
            elif st.state != _SOD:
                what = f"{st.state}, statusword 0x{self._sw[i]:04X}"
            else:
                continue
            self.stop_report.append(
                f"{self._drive(i)}: not SWITCH ON DISABLED at NMT pre-operational ({what})"
            )

    def _close_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.shutdown()

    def notes(self) -> list[str]:
        """The stop's problems, and the warning error frames the bus reported (not faults)."""
        out = list(self.stop_report)
        for cob, (count, length, mapped) in self._long_pdos.items():
            route = self._routes.get(cob)
            who = "torque sensor" if route is None or route[0] == _SENSOR else self._drive(route[1])
            out.append(
                f"{who}: {count} PDO(s) 0x{cob:03X} of {length} bytes, longer than their mapping "
                f"({mapped} bytes): the mapped leading bytes were used (CiA 301)"
            )
        if self.stats["bus_warnings"]:
            out.append(
                f"{self._bus_name}: {self.stats['bus_warnings']} warning error frames, not "
                f"faults (the last: {self.last_bus_warning})"
            )
        return out


def make_can(
    cfg: SessionConfig, side: str, model: RobotModel, operator: Load | None = None
) -> CanBackend:
    """Side ``side``'s robot on CiA 402 drives (the registry's "can")."""
    return CanBackend(cfg, side, model.nv, operator)
