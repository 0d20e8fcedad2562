"""The CAN backend against the drive emulator, in one process on python-can's ``virtual`` bus.

The emulator is stepped by the master's own frames (``SteppedBus``): every SYNC the master sends
makes the emulated drives answer before the master looks, so each run is deterministic. What is
checked: the start-up sequence and PDO mapping as the drive sees them, the CiA 402 state machine
from SWITCH ON DISABLED to OPERATION ENABLED with zero torque until then, the units of the
feedback, and every fault of the issue ending in a SafetyStop within 3 ticks that names the
robot, joint, drive node and reason, followed by a safe stop (quick stop, disable, NMT
pre-operational).
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest
import yaml

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.errors import BackendError, ConfigError, SafetyStop
from teleop_rt.hal.can.backend import CanBackend
from teleop_rt.hal.can.config import DEFAULT_EDS
from teleop_rt.hal.can.emulator import FAULT, OE, QSA, SOD, DriveEmulator, Fault, emulated_bus
from teleop_rt.hal.registry import create_backend
from teleop_rt.model import RobotModel

ROOT = Path(__file__).resolve().parents[1]
CAN_CONFIG = ROOT / "configs" / "can_emulated.yaml"
ZERO_TICKS = 20
FAST = [
    "can.emulate=true",
    f"can.hsi.torque_sensor.zero_ticks={ZERO_TICKS}",
    f"can.to.torque_sensor.zero_ticks={ZERO_TICKS}",
    "can.heartbeat_ms=10",  # short heartbeats: a lost one shows within a few dozen ticks
    "can.heartbeat_timeout_ms=15",
]


def make_cfg(*overrides: str) -> config.SessionConfig:
    return config.load(CAN_CONFIG, [*FAST, *overrides])


def make_backend(cfg: config.SessionConfig, side: str = "hsi") -> CanBackend:
    model = RobotModel.from_spec(getattr(cfg, side).robot, side)
    backend = create_backend("can", cfg, side, model)
    assert isinstance(backend, CanBackend)
    return backend


@pytest.fixture
def started():
    backends: list[CanBackend] = []

    def start(*overrides: str, side: str = "hsi") -> CanBackend:
        backend = make_backend(make_cfg(*overrides), side)
        backends.append(backend)
        backend.configure()
        backend.activate()
        return backend

    yield start
    for b in backends:
        b.shutdown()


def run_ticks(backend: CanBackend, ticks: int, tau: float = 0.0) -> None:
    for _ in range(ticks):
        backend.read()
        backend.write([tau] * backend.n)


# --- start-up ---------------------------------------------------------------------------------
def test_startup_sequence_as_the_drive_sees_it(started) -> None:
    backend = started()
    emu = backend.emulator
    for drive in emu.drives:
        assert drive.nmt_log == ["reset node", "start"]
        writes = drive.sdo_writes
        values = {(i, s): v for i, s, v in writes}
        assert values[(0x6060, 0)] == 10  # cyclic synchronous torque
        assert values[(0x605A, 0)] == 2  # quick stop, then switch on disabled
        assert values[(0x6007, 0)] == 1  # communication loss: fault
        assert values[(0x1005, 0)] == 0x80  # SYNC COB-ID, consumer
        assert values[(0x1006, 0)] == 1000  # SYNC period in us
        assert values[(0x1017, 0)] == 10  # heartbeat producer, ms
        assert values[(0x1016, 1)] == 127 << 16 | 200  # watches the master (node 127), 200 ms
        # mode and SYNC are set before any PDO is touched; every PDO is disabled before its
        # mapping is rewritten and enabled again only after it (CiA 301's procedure)
        order = [(i, s) for i, s, _ in writes]
        assert order.index((0x6060, 0)) < order.index((0x1400, 1))
        for com, mapping in ((0x1400, 0x1600), (0x1800, 0x1A00), (0x1801, 0x1A01)):
            cob_writes = [k for k, (i, s, _) in enumerate(writes) if (i, s) == (com, 1)]
            map_writes = [k for k, (i, s, _) in enumerate(writes) if i == mapping]
            assert writes[cob_writes[0]][2] & 0x80000000  # disabled first
            assert cob_writes[0] < min(map_writes) < max(map_writes) < cob_writes[-1]
            assert not writes[cob_writes[-1]][2] & 0x80000000  # enabled last
        # the PDOs as the drive compiled them at NMT start
        node = drive.node_id
        assert not drive.mapping_errors
        (rpdo,) = drive.rpdos.values()
        assert (rpdo.cob_id, rpdo.objects, rpdo.trans_type) == (0x200 + node, [0x6040, 0x6071], 1)
        assert rpdo.layout.format == "<Hh"
        tpdos = {p.cob_id: p for p in drive.tpdos}
        assert set(tpdos) == {0x180 + node, 0x280 + node}  # TPDO3/4 disabled
        t1, t2 = tpdos[0x180 + node], tpdos[0x280 + node]
        assert (t1.objects, t1.trans_type, t1.layout.format) == ([0x6064, 0x606C], 1, "<ii")
        assert (t2.objects, t2.trans_type, t2.layout.format) == ([0x6041, 0x6077], 2, "<Hh")
    assert [d.rated_torque_raw for d in backend.drive_info] == [50, 50]  # 0x6076 read back


def test_state_machine_to_operation_enabled_with_zero_torque_until_then(started) -> None:
    backend = started()
    for drive in backend.emulator.drives:
        assert drive.state == OE
        cws = [cw for cw, _, _ in drive.commands]
        # while the sensor is zeroed the drive stays disabled, then one controlword per tick:
        # shutdown, switch on, enable operation (each repeated until the statusword shows it)
        assert set(cws[:ZERO_TICKS]) == {0x00}
        steps = [cw for k, cw in enumerate(cws) if k == 0 or cw != cws[k - 1]]
        assert steps == [0x00, 0x06, 0x07, 0x0F]
        assert all(torque == 0 for _, torque, _ in drive.commands)
    assert backend.running
    run_ticks(backend, 5, tau=0.5)
    for drive in backend.emulator.drives:  # once enabled, the torque goes out (0.5 N m = 500 ‰)
        assert drive.commands[-1] == (0x0F, 500, OE)


def test_feedback_in_joint_units_and_sensor_zeroed(started) -> None:
    backend = started()
    fb = backend.read()
    backend.write([0.0, 0.0])
    q0 = backend.cfg.hsi.robot.q0_rad
    count = 2 * 3.141592653589793 / (4096 * 20)
    assert fb.q == pytest.approx(q0, abs=count)
    assert fb.v.tolist() == [0.0, 0.0]
    # the emulated sensor carries a 0.02 N m bias: zeroing at start-up removed it
    assert fb.tau_ext == pytest.approx([0.0, 0.0], abs=1e-5)


def test_a_torque_moves_the_emulated_joint_one_tick_later(started) -> None:
    backend = started()
    backend.read()
    backend.write([0.2, 0.0])
    v1 = backend.read().v[0]  # SYNC 1: the torque is only now latched
    backend.write([0.2, 0.0])
    v2 = backend.read().v[0]
    assert v1 == 0.0 and v2 > 0.0


def test_a_fault_at_start_is_reset_by_a_rising_edge_of_bit_7() -> None:
    cfg = make_cfg("can.nmt_reset_at_start=communication")  # a reset node would clear it
    backend = make_backend(cfg)
    backend._open_bus()
    drive = backend.emulator.drives[1]
    drive.state = FAULT
    try:
        backend.configure()
        backend.activate()
        cws = [cw for cw, _, _ in drive.commands]
        k = cws.index(0x80)
        assert cws[k - 1] == 0x00 and drive.state == OE
    finally:
        backend.shutdown()


# --- faults -----------------------------------------------------------------------------------
FAULTS = [
    ("drop_tpdo", 2, r"hsi joint 1 \(drive node 2\): no feedback \(TPDO\) for 3 ticks in a row"),
    ("emcy", 1, r"hsi joint 0 \(drive node 1\): EMCY 0x2310 \(Current\)"),
    ("status_fault", 2, r"hsi joint 1 \(drive node 2\): drive fault \(statusword 0x021[8F]: FAULT"),
    (
        "error_frame",
        None,
        r"can: hsi bus \(stepped emulator on Virtual bus channel [^)]+\): CAN error frame 0x004 "
        r"\(controller problem: RX error passive\)",
    ),
    ("drop_sensor", None, r"hsi torque sensor 0x18A: no data for 3 ticks in a row"),
]


@pytest.mark.parametrize(("kind", "node", "reason"), FAULTS, ids=[f[0] for f in FAULTS])
def test_every_fault_is_a_safe_stop_within_3_ticks(started, kind, node, reason) -> None:
    backend = started()
    run_ticks(backend, 10, tau=0.1)
    backend.emulator.inject(Fault(kind, node))  # from the next SYNC on
    for k in range(1, 4):
        try:
            run_ticks(backend, 1, tau=0.1)
        except SafetyStop as exc:
            assert k <= 3
            with pytest.raises(SafetyStop, match=reason):
                raise exc
            break
    else:
        pytest.fail(f"{kind}: no SafetyStop within 3 ticks")
    assert_stopped_safely(backend)


def test_a_lost_heartbeat_stops_within_3_ticks_of_its_timeout(started) -> None:
    backend = started()
    run_ticks(backend, 10)
    backend.emulator.inject(Fault("stop_heartbeat", 1))
    with pytest.raises(SafetyStop, match=r"hsi joint 0 \(drive node 1\): heartbeat lost") as info:
        run_ticks(backend, 100)
    overdue = (backend._now() - backend._last_hb_ns[0] - backend.hb_timeout_ns) / 1e6  # ticks
    assert 1 <= overdue <= 3, info.value
    assert_stopped_safely(backend)


def test_a_stopped_heartbeat_stays_stopped_over_an_nmt_change(started) -> None:
    """A SYNC after an NMT command is answered from a fresh sample (no plant step): the lasting
    faults of the tick still hold there, so the drive whose heartbeat was stopped sends none
    (before, that answer cleared the silence for one SYNC, and a heartbeat due then went out)."""
    backend = started("can.heartbeat_timeout_ms=1000")  # the master does not stop meanwhile
    emu = backend.emulator
    run_ticks(backend, 10)
    emu.inject(Fault("stop_heartbeat", 1))
    emu.sent = []
    start_node_1 = can.Message(arbitration_id=0x000, data=bytes([0x01, 1]), is_extended_id=False)
    drive = emu.by_node[1]
    for _ in range(30):  # 3 heartbeat periods (10 ms)
        if emu.time_us + emu.period_us - drive.last_heartbeat_us >= drive.heartbeat_us:
            emu.handle(start_node_1)  # before the SYNC its heartbeat is due at: an NMT change
        run_ticks(backend, 1)
    beats = [cob for cob, _ in emu.sent if cob in (0x701, 0x702)]
    assert beats.count(0x702) == 3  # the other drive's, every 10 ms
    assert 0x701 not in beats


def test_a_bus_error_is_a_safe_stop(started) -> None:
    backend = started()
    run_ticks(backend, 3)
    backend.bus._inner.shutdown()  # the interface goes away under the loop
    with pytest.raises(SafetyStop, match=r"can: hsi bus \(.+\): bus error"):
        run_ticks(backend, 1)
    backend.shutdown()  # must not raise
    assert backend.stop_report


def test_an_error_frame_from_another_node_names_the_bus_and_its_class(started) -> None:
    backend = started()
    run_ticks(backend, 3)
    bus_off = can.Message(arbitration_id=0x040, is_error_frame=True, data=bytes(8))
    backend.emulator.bus.send(bus_off)  # seen in the drain before the next SYNC
    with pytest.raises(SafetyStop, match=r"can: hsi bus \(.+\): CAN error frame 0x040 \(bus off\)"):
        run_ticks(backend, 1)
    assert_stopped_safely(backend)


def test_a_warning_error_frame_is_counted_and_reported_not_a_stop(started) -> None:
    backend = started()
    run_ticks(backend, 3)
    lost_arbitration = can.Message(arbitration_id=0x002, is_error_frame=True, data=bytes(8))
    warning = can.Message(arbitration_id=0x004, is_error_frame=True, data=b"\x00\x08" + bytes(6))
    backend.emulator.bus.send(lost_arbitration)
    backend.emulator.bus.send(warning)
    run_ticks(backend, 5)  # no SafetyStop
    assert backend.stats["bus_warnings"] == 2
    notes = backend.notes()
    assert len(notes) == 1
    assert re.fullmatch(
        r"can: hsi bus \(.+\): 2 warning error frames, not faults \(the last: CAN error frame "
        r"0x004 \(controller problem: TX error warning\)\)",
        notes[0],
    ), notes
    passive = can.Message(arbitration_id=0x004, is_error_frame=True, data=b"\x00\x20" + bytes(6))
    backend.emulator.bus.send(passive)  # error passive is a fault again
    with pytest.raises(SafetyStop, match=r"TX error passive"):
        run_ticks(backend, 1)
    assert_stopped_safely(backend)


def test_a_bus_the_interface_reports_in_error_is_a_safe_stop(started, monkeypatch) -> None:
    backend = started()
    run_ticks(backend, 5)
    polls = []

    def state(bus) -> can.BusState:
        polls.append(backend.tick)
        return can.BusState.ERROR if len(polls) > 3 else can.BusState.ACTIVE

    monkeypatch.setattr(type(backend.bus), "state", property(state))
    start = backend.tick
    with pytest.raises(SafetyStop, match=r"can: hsi bus \(.+\): bus state ERROR") as info:
        run_ticks(backend, 100)
    # polled every missed_feedback_ticks (3) ticks, not every tick; stopped at the 4th poll
    assert [b - a for a, b in zip(polls, polls[1:], strict=False)] == [3, 3, 3]
    assert 1 <= polls[0] - start <= 3
    assert backend.tick == polls[-1], info.value
    monkeypatch.undo()
    assert_stopped_safely(backend)


def test_a_pdo_shorter_than_its_mapping_is_a_safe_stop(started) -> None:
    backend = started()
    run_ticks(backend, 4)
    short = can.Message(arbitration_id=0x282, data=b"\x37\x02\x00", is_extended_id=False)
    backend.emulator.bus.send(short)  # seen in the drain before the next SYNC
    with pytest.raises(
        SafetyStop,
        match=r"hsi joint 1 \(drive node 2\): malformed frame 0x282: TPDO2 .*: expected 4 data "
        r"bytes, received 3",
    ):
        run_ticks(backend, 1)
    assert_stopped_safely(backend)


def test_a_short_sensor_pdo_is_a_safe_stop_not_a_crash(started) -> None:
    backend = started()
    run_ticks(backend, 4)
    backend.emulator.bus.send(can.Message(arbitration_id=0x18A, data=bytes(5)))
    with pytest.raises(
        SafetyStop, match=r"torque sensor: malformed frame 0x18A: .*expected 8 data bytes, rec"
    ):
        run_ticks(backend, 1)
    assert_stopped_safely(backend)


def test_drives_fault_when_the_master_heartbeat_stops(started) -> None:
    backend = started()
    backend.master_hb_ns = 1 << 62  # the master goes silent (but keeps SYNCing)
    with pytest.raises(SafetyStop, match=r"EMCY 0x8130 \(Monitoring\)"):
        run_ticks(backend, 300)
    # the drives' own watch (0x1016, 200 ms) fired 200 ms after the master's last heartbeat
    assert 200 < (backend._now() - backend.master_hb_at_ns) / 1e6 <= 203  # ticks of 1 ms


def test_nan_torque_never_reaches_a_drive(started) -> None:
    backend = started()
    backend.read()
    with pytest.raises(SafetyStop, match="NaN"):
        backend.write([float("nan"), 0.0])


def assert_stopped_safely(backend: CanBackend) -> None:
    backend.shutdown()
    emu = backend.emulator
    for drive in emu.drives:
        assert drive.state in (SOD, FAULT)
        assert drive.nmt_log[-1] == "pre-op"
        tail = [c for c in drive.commands[-20:] if c[2] != FAULT]
        # after the stop: zero torque and quick stop / disable voltage only
        stop_part = [c for c in tail if c[0] in (0x02, 0x00)]
        assert all(torque == 0 for _, torque, _ in stop_part)
    backend.shutdown()  # idempotent


def test_normal_stop_quick_stops_then_disables(started) -> None:
    backend = started()
    run_ticks(backend, 5, tau=0.3)
    backend.shutdown()
    for drive in backend.emulator.drives:
        cws = [cw for cw, _, _ in drive.commands]
        last_enabled = max(k for k, cw in enumerate(cws) if cw == 0x0F)
        assert cws[last_enabled + 1 :] and set(cws[last_enabled + 1 :]) <= {0x02, 0x00}
        assert cws[last_enabled + 1] == 0x02 and cws[-1] == 0x00
        assert drive.state == SOD and drive.nmt_log[-1] == "pre-op"
        assert all(t == 0 for _, t, _ in drive.commands[last_enabled + 1 :])


def test_a_quick_stop_that_does_not_finish_ends_disabled(started) -> None:
    """A drive that stays in QUICK STOP ACTIVE (quick stop option 5..8, or a slow ramp) when
    stop_ticks runs out gets disable voltage until SWITCH ON DISABLED, then NMT pre-op."""
    backend = started("can.stop_ticks=10")
    run_ticks(backend, 5, tau=0.3)
    held = backend.emulator.drives[0]
    held.quick_stop_option = 6  # the drive stays halted in QUICK STOP ACTIVE
    backend.shutdown()
    all_cws = [cw for cw, _, _ in held.commands]
    stop = held.commands[max(k for k, cw in enumerate(all_cws) if cw == 0x0F) + 1 :]
    cws = [cw for cw, _, _ in stop]
    assert cws[:10] == [0x02] * 10 and set(cws[10:]) == {0x00}  # quick stop, then disable
    # ... the first disable voltage reaching it in QUICK STOP ACTIVE, the rest as it reports SOD
    assert [state for _, _, state in stop] == [OE] + [QSA] * 10 + [SOD] * (len(stop) - 11)
    assert held.state == SOD and held.nmt_log[-1] == "pre-op"
    assert all(t == 0 for _, t, _ in stop)
    assert backend.notes() == [
        "can: hsi: quick stop not complete after 10 ticks (node 1: QUICK STOP ACTIVE): "
        "disable voltage sent"
    ]


def test_a_drive_that_is_not_disabled_at_the_end_is_named(started) -> None:
    backend = started("can.stop_ticks=5", "can.disable_ticks=4")
    run_ticks(backend, 5)
    stuck = backend.emulator.drives[1]
    stuck.quick_stop_option = 6
    stuck._controlword = lambda cw: None  # then ignores every controlword: stays enabled
    backend.shutdown()
    assert stuck.state == OE and stuck.nmt_log[-1] == "pre-op"  # NMT pre-op all the same
    assert backend.notes()[-1] == (
        "can: hsi joint 1 (drive node 2): not SWITCH ON DISABLED at NMT pre-operational "
        "(OPERATION ENABLED, statusword 0x0237)"
    )
    assert backend.emulator.drives[0].state == SOD


# --- configuration errors -----------------------------------------------------------------
def test_drive_count_must_match_the_joints() -> None:
    cfg = make_cfg("can.hsi.drives=[{node_id: 1, counts_per_rev: 4096}]")
    with pytest.raises(ConfigError, match=r"can.hsi.drives: 1 drive\(s\) but the robot has 2"):
        make_backend(cfg)


def test_duplicate_node_ids_are_rejected() -> None:
    with pytest.raises(ConfigError, match="node ids must be unique"):
        make_cfg("can.to.drives.1.node_id=1")


def test_a_missing_drive_is_one_clear_error() -> None:
    cfg = make_cfg("can.hsi.drives.1.node_id=9", "can.boot_timeout_s=0.2")
    backend = make_backend(cfg)
    backend.bus = emulated_bus(make_cfg(), "hsi")  # the bus has nodes 1 and 2 only
    try:
        with pytest.raises(BackendError, match=r"hsi drive node 9: no boot-up within 0.2 s"):
            backend.configure()  # the start-up: before any drive is enabled
    finally:
        backend.shutdown()


def aborting(drive, index: int, sub: int, code: int):
    """Make an emulated drive abort SDO writes to index:sub with ``code``."""
    from canopen.sdo.exceptions import SdoAbortedError

    def check(**request) -> None:  # canopen passes index, subindex, od, data
        if (request["index"], request["subindex"]) == (index, sub):
            raise SdoAbortedError(code)

    drive.node.add_write_callback(check)


@pytest.mark.parametrize(
    ("index", "sub", "code", "message"),
    [
        (
            0x605A,
            0,
            0x06090030,
            "can: hsi drive node 2: SDO write 0x605A:00 (Quick stop option code) = 2 aborted by "
            "the drive: Code 0x06090030, Value range of parameter exceeded",
        ),
        (  # inside canopen's PDO mapping, which does not say which object it wrote
            0x1A01,
            2,
            0x06040041,
            "can: hsi drive node 2: SDO write 0x1A01:02 (TPDO2 mapping parameter: Mapped object "
            "2) aborted by the drive: Code 0x06040041, Object cannot be mapped to the PDO",
        ),
    ],
    ids=["write", "pdo-mapping"],
)
def test_an_sdo_abort_at_start_names_the_drive_and_the_object(index, sub, code, message) -> None:
    backend = make_backend(make_cfg())
    backend._open_bus()
    aborting(backend.emulator.drives[1], index, sub, code)
    try:
        with pytest.raises(BackendError) as info:
            backend.configure()
        assert str(info.value) == message
    finally:
        backend.shutdown()


def test_cli_an_sdo_abort_at_start_is_one_line(tmp_path) -> None:
    """A drive whose EDS makes 0x605A read-only aborts the master's write (in-process
    emulator, its own EDS): one line naming drive and object, no traceback."""
    eds = DEFAULT_EDS.read_text().replace(
        "ParameterName=Quick stop option code\nObjectType=0x7\nDataType=0x0003\nAccessType=rw",
        "ParameterName=Quick stop option code\nObjectType=0x7\nDataType=0x0003\nAccessType=ro",
    )
    (tmp_path / "ro.eds").write_text(eds)
    path = write_config(tmp_path, "ro.eds")
    sets = [a for o in FAST for a in ("--set", o)]
    run = subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", "run", str(path), *sets, "--duration", "0.1",
         "--no-log"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert run.returncode != 0
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert (
        "can: hsi drive node 1: SDO write 0x605A:00 (Quick stop option code) = 2 aborted by the "
        "drive: Code 0x06010002, Attempt to write a read only object"
    ) in lines[0]


def test_cli_no_boot_up_names_the_bus_by_interface_and_channel() -> None:
    """No drive on the bus (a port nobody serves): the message names the configured bus."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # free now; no emulator listens there
    run = subprocess.run(
        [sys.executable, "-m", "teleop_rt.cli", "run", str(CAN_CONFIG), "--no-log",
         "--duration", "0.1", "--set", "can.boot_timeout_s=0.3",
         "--set", f"can.hsi.bus.options={{port: {port}, hop_limit: 0}}"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert run.returncode != 0
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert (
        "can: hsi drive node 1: no boot-up within 0.3 s after NMT reset (is the drive powered "
        "and on udp_multicast 239.74.163.1?)"
    ) in lines[0]


def test_an_unopenable_bus_is_one_clear_error() -> None:
    cfg = make_cfg("can.emulate=false", "can.hsi.bus.interface=nonexistent_interface")
    backend = make_backend(cfg)
    with pytest.raises(BackendError, match=r"can: hsi bus \(interface=nonexistent_interface"):
        backend.configure()
        backend.activate()
    backend.shutdown()


def test_registering_the_backend_does_not_import_python_can() -> None:
    code = (
        "import sys; from teleop_rt.hal.registry import available_backends; "
        "assert 'can' in available_backends(); "
        "assert 'canopen' not in sys.modules and 'can' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_the_emulator_tool_parses_fault_options() -> None:
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "drive_emulator", ROOT / "tools" / "drive_emulator.py"
    )
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert tool.parse_fault("emcy:2@3000") == (None, Fault("emcy", 2, 3000, None))
    assert tool.parse_fault("to:drop_tpdo:*@5+2") == ("to", Fault("drop_tpdo", None, 5, 2))
    for bad in ("emcy:2", "melt:1@3", "emcy:x@1"):
        with pytest.raises(Exception, match="--fault"):
            tool.parse_fault(bad)


# --- EDS files ------------------------------------------------------------------------------
def write_config(folder: Path, eds: str) -> Path:
    """can_emulated.yaml in ``folder`` with HSI drive 0's EDS at ``eds`` (URDFs made absolute)."""
    data = yaml.safe_load(CAN_CONFIG.read_text())
    for side in ("hsi", "to"):
        robot = data[side]["robot"]
        robot["urdf"] = str((CAN_CONFIG.parent / robot["urdf"]).resolve())
    data["can"]["hsi"]["drives"][0]["eds"] = eds
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "session.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_relative_eds_path_is_read_from_the_config_folder(tmp_path, monkeypatch) -> None:
    path = write_config(tmp_path / "cell", "eds/drive.eds")
    (tmp_path / "cell" / "eds").mkdir()
    (tmp_path / "cell" / "eds" / "drive.eds").write_text(DEFAULT_EDS.read_text())
    monkeypatch.chdir(tmp_path)  # eds/drive.eds does not exist relative to the cwd
    cfg = config.load(path, FAST)
    assert cfg.can.hsi.drives[0].eds == tmp_path / "cell" / "eds" / "drive.eds"
    assert cfg.can.hsi.drives[1].eds is None  # the bundled default
    backend = make_backend(cfg)
    try:
        backend.configure()  # master and emulator both read it
        backend.activate()
        assert backend.running
    finally:
        backend.shutdown()


def test_a_missing_eds_is_one_config_error_naming_the_key(tmp_path, capsys) -> None:
    path = write_config(tmp_path, "vendor.eds")
    missing = tmp_path / "vendor.eds"
    cfg = config.load(path, FAST)
    with pytest.raises(ConfigError, match=rf"^can.hsi.drives.0.eds: no such file: {missing}$"):
        make_backend(cfg)
    bus = can.Bus(interface="virtual", channel="eds-missing")
    try:
        with pytest.raises(ConfigError, match=r"^can.hsi.drives.0.eds: no such file"):
            DriveEmulator(bus, cfg, "hsi")
    finally:
        bus.shutdown()
    code = main(["run", str(path), "--set", "can.emulate=true", "--duration", "0.01", "--no-log"])
    assert code == 2
    assert f"can.hsi.drives.0.eds: no such file: {missing}" in capsys.readouterr().err


# --- between a robot's start and the loop (real time, emulator in a thread) -------------------
@pytest.fixture
def free_running(tmp_path):
    """Start the HSI in real time against an emulator thread on a ``virtual`` bus (the wall
    clock runs: the drives' 0x1016 watch times out if the master stops SYNC and heartbeat)."""
    import threading

    stops: list = []

    def start(*overrides: str) -> CanBackend:
        channel = f"free-running-{tmp_path.name}"
        cfg = make_cfg(
            "can.emulate=false",
            f"can.hsi.bus={{interface: virtual, channel: {channel}}}",
            "can.feedback_window_us=20000",  # the emulator thread shares the GIL (and 2 CPUs)
            "can.missed_feedback_ticks=20",
            "can.heartbeat_ms=20",
            "can.heartbeat_timeout_ms=60",
            *overrides,
        )
        emu = DriveEmulator(can.Bus(interface="virtual", channel=channel), cfg, "hsi")
        stop = threading.Event()
        thread = threading.Thread(target=emu.serve, args=(stop,), daemon=True)
        thread.start()
        backend = make_backend(cfg)
        backend.emu = emu
        stops.append((backend, stop, thread, emu))
        backend.configure()
        backend.activate()
        return backend

    yield start
    for backend, stop, thread, emu in stops:
        backend.shutdown()
        stop.set()
        thread.join()
        emu.bus.shutdown()


IDLE_S = 0.5  # the other robot's start-up, > 2x master_heartbeat_timeout_ms (200 ms)


@pytest.mark.parametrize("keepalive", [True, False], ids=["keepalive", "without"])
def test_a_started_robot_stays_guarded_while_the_other_starts(
    free_running, monkeypatch, keepalive
) -> None:
    if not keepalive:  # the control: without it the drives' 0x1016 watch fires
        monkeypatch.setattr(CanBackend, "_start_keepalive", lambda self: None)
    backend = free_running()
    time.sleep(IDLE_S)  # the session starts the TO meanwhile
    with backend.emu._lock:
        states = [d.state for d in backend.emu.drives]
    if keepalive:
        assert states == [OE, OE]
        run_ticks(backend, 3)  # the loop takes over without a fault
    else:
        assert states == [FAULT, FAULT]
        with pytest.raises(SafetyStop, match=r"EMCY 0x8130 \(Monitoring\)"):
            run_ticks(backend, 3)


def test_a_fault_while_the_other_robot_starts_stops_this_one_and_is_raised(free_running):
    backend = free_running()
    emu = backend.emu
    drive = emu.drives[0]
    with emu._lock:
        seen = len(drive.commands)
        emu.inject(Fault("emcy", 1))
    time.sleep(0.2)
    with pytest.raises(SafetyStop, match=r"hsi joint 0 \(drive node 1\): EMCY 0x2310"):
        run_ticks(backend, 1)  # the loop's first read
    backend.shutdown()
    with emu._lock:
        after = [cw for cw, _, _ in drive.commands[seen:]]
        states = [d.state for d in emu.drives]
    # Quick stop / disable from the master's reaction on: never a fault reset (0x80) and
    # re-enable. Enable-operation frames (0x0F) the keepalive sent before the EMCY reached
    # it may still be queued on the bus when the fault is injected, so they may lead.
    reaction = next((i for i, cw in enumerate(after) if cw in (0x02, 0x00)), None)
    assert reaction is not None, after
    assert set(after[:reaction]) <= {0x0F}, after[:reaction]
    assert set(after[reaction:]) <= {0x02, 0x00}, sorted(set(after[reaction:]))
    assert states == [FAULT, SOD]


@pytest.mark.parametrize("poll_s", [0.0, 1e-4], ids=["blocking", "polling"])
def test_the_free_running_emulator_answers_sync_blocking_or_polling(poll_s) -> None:
    """``serve`` (the emulator's own thread, as tools/drive_emulator.py runs it) answers a SYNC
    with the sensor's TPDO whether it blocks on the bus or polls it, and stops on request."""
    import threading

    channel = f"serve-{poll_s}"
    emulator_bus = can.Bus(interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel)
    emulator = DriveEmulator(emulator_bus, make_cfg(), "hsi")
    stop = threading.Event()
    thread = threading.Thread(target=emulator.serve, args=(stop, 5, poll_s))
    thread.start()
    try:
        while master.recv(0.05) is not None:  # the drives' boot-up frames
            pass
        master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        sensor = emulator.sensor.cob_id
        answers = []
        while (msg := master.recv(2.0)) is not None and msg.arbitration_id != sensor:
            answers.append(msg.arbitration_id)
        assert msg is not None, f"no sensor TPDO after SYNC; got {answers}"
        assert emulator.sync_count == 1
    finally:
        stop.set()
        thread.join(2.0)
        emulator_bus.shutdown()
        master.shutdown()
    assert not thread.is_alive()


SLOW_TICK_S = 0.01  # a loaded host in fast mode: ticks 10 times longer than the period


def test_heartbeats_are_wall_clock_times_when_ticks_are_slow(free_running) -> None:
    """Ticks of 10 ms against a 1 ms period: the master's heartbeat (50 ms) still goes out by
    the wall clock, so the drives' 200 ms watch (0x1016) stays quiet; counted in ticks it
    would go out every 500 ms and every drive would fault. A drive's heartbeat (every 20 ms)
    that stops is missed after 150 ms of wall time, not after 150 ticks."""
    backend = free_running("can.heartbeat_timeout_ms=150")
    emu = backend.emu
    for _ in range(60):  # 0.6 s and more
        time.sleep(SLOW_TICK_S)
        run_ticks(backend, 1)
    with emu._lock:
        assert [d.state for d in emu.drives] == [OE, OE]
        emu.inject(Fault("stop_heartbeat", 2))
    start = backend.tick
    with pytest.raises(SafetyStop, match=r"hsi joint 1 \(drive node 2\): heartbeat lost") as info:
        for _ in range(150):
            time.sleep(SLOW_TICK_S)
            run_ticks(backend, 1)
    assert backend.tick - start < 50, info.value  # 150 ms at >= 10 ms a tick: about 15


def test_a_stopped_heartbeat_stays_stopped_while_no_sync_comes(free_running) -> None:
    """Between SYNCs the free-running emulator's drives send their heartbeats by the wall clock
    (ticks slower than the heartbeat period, or none at all): a drive whose heartbeat was
    stopped stays silent there too, the other's goes on. (Before, that path sent both: with
    ticks of 10 ms on a loaded host the test above saw the loss after 106 ticks, or never.)"""
    backend = free_running()
    emu = backend.emu
    run_ticks(backend, 5)
    with emu._lock:
        emu.inject(Fault("stop_heartbeat", 2))
        emu.sent = []
    time.sleep(0.12)  # no tick: 6 heartbeat periods (20 ms), within the drives' 200 ms watch
    with emu._lock:
        beats = [cob for cob, _ in emu.sent if cob in (0x701, 0x702)]
        emu.sent = None
    assert 0x701 in beats, beats  # the wall-clock path ran
    assert 0x702 not in beats, beats


# --- frames stay on this host -------------------------------------------------------------
def multicast_ttl(bus: can.BusABC) -> int:
    """The multicast TTL of a python-can udp_multicast bus's socket."""
    import socket
    import struct

    sock = bus._multicast._socket
    raw = sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 4)
    return struct.unpack("@I", raw)[0]


def test_udp_multicast_buses_keep_their_frames_on_this_host() -> None:
    """python-can's udp_multicast sends with a TTL of 1 (out on the network) unless told: the
    default ``can:`` section, configs/can_emulated.yaml and a bus without a hop_limit of its
    own all resolve to hop_limit 0 (a TTL of 0 never leaves the host); one given is kept."""
    from teleop_rt.hal.can.config import CanBusSpec, CanSpec

    given = CanBusSpec(interface="udp_multicast", channel="239.74.163.7", options={"port": 47811})
    cases = [CanSpec().hsi.bus, CanSpec().to.bus, make_cfg().can.hsi.bus, make_cfg().can.to.bus]
    for bus in [*cases, given]:
        assert bus.kwargs()["hop_limit"] == 0, bus
    own = CanBusSpec(interface="udp_multicast", channel="239.74.163.7", options={"hop_limit": 2})
    assert own.kwargs()["hop_limit"] == 2  # the user's choice
    assert "hop_limit" not in CanBusSpec(interface="socketcan", channel="can0").kwargs()
    # --backend can on a config without a can: section: the bus the backend opens
    plain = config.load(ROOT / "configs" / "paper_experiment.yaml", ["backend=can"])
    assert plain.can is None
    for side in ("hsi", "to"):
        backend = make_backend(plain, side)
        backend._open_bus()
        try:
            assert multicast_ttl(backend.bus) == 0
        finally:
            backend.shutdown()
