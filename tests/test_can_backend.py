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

import subprocess
import sys
from pathlib import Path

import pytest

from teleop_rt import config
from teleop_rt.errors import BackendError, ConfigError, SafetyStop
from teleop_rt.hal.base import create_backend
from teleop_rt.hal.can.backend import CanBackend
from teleop_rt.hal.can.emulator import FAULT, OE, SOD, Fault, emulated_bus
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
        backend.start()
        return backend

    yield start
    for b in backends:
        b.stop()


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
    assert fb.q_list == pytest.approx(q0, abs=count)
    assert list(fb.q) == fb.q_list
    assert fb.v_list == [0.0, 0.0]
    # the emulated sensor carries a 0.02 N m bias: zeroing at start-up removed it
    assert fb.tau_ext == pytest.approx([0.0, 0.0], abs=1e-5)


def test_a_torque_moves_the_emulated_joint_one_tick_later(started) -> None:
    backend = started()
    backend.read()
    backend.write([0.2, 0.0])
    v1 = backend.read().v_list[0]  # SYNC 1: the torque is only now latched
    backend.write([0.2, 0.0])
    v2 = backend.read().v_list[0]
    assert v1 == 0.0 and v2 > 0.0


def test_a_fault_at_start_is_reset_by_a_rising_edge_of_bit_7() -> None:
    cfg = make_cfg("can.nmt_reset_at_start=communication")  # a reset node would clear it
    backend = make_backend(cfg)
    backend._open_bus()
    drive = backend.emulator.drives[1]
    drive.state = FAULT
    try:
        backend.start()
        cws = [cw for cw, _, _ in drive.commands]
        k = cws.index(0x80)
        assert cws[k - 1] == 0x00 and drive.state == OE
    finally:
        backend.stop()


# --- faults -----------------------------------------------------------------------------------
FAULTS = [
    ("drop_tpdo", 2, r"hsi joint 1 \(drive node 2\): no feedback \(TPDO\) for 3 ticks in a row"),
    ("emcy", 1, r"hsi joint 0 \(drive node 1\): EMCY 0x2310 \(Current\)"),
    ("status_fault", 2, r"hsi joint 1 \(drive node 2\): drive fault \(statusword 0x021[8F]: FAULT"),
    ("error_frame", None, r"hsi bus: CAN error frame"),
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
    overdue = backend.tick - backend._last_hb[0] - backend.hb_timeout_ticks
    assert 1 <= overdue <= 3, info.value
    assert_stopped_safely(backend)


def test_a_bus_error_is_a_safe_stop(started) -> None:
    backend = started()
    run_ticks(backend, 3)
    backend.bus._inner.shutdown()  # the interface goes away under the loop
    with pytest.raises(SafetyStop, match=r"can: hsi bus error"):
        run_ticks(backend, 1)
    backend.stop()  # must not raise
    assert backend.stop_report


def test_drives_fault_when_the_master_heartbeat_stops(started) -> None:
    backend = started()
    backend.master_hb_ticks = 10**9  # the master goes silent (but keeps SYNCing)
    with pytest.raises(SafetyStop, match=r"EMCY 0x8130 \(Monitoring\)"):
        run_ticks(backend, 300)
    # the drives' own watch (0x1016, 200 ms) fired 200 ms after the master's last heartbeat
    assert 200 < backend.tick - backend.master_hb_tick <= 203


def test_nan_torque_never_reaches_a_drive(started) -> None:
    backend = started()
    backend.read()
    with pytest.raises(SafetyStop, match="NaN"):
        backend.write([float("nan"), 0.0])


def assert_stopped_safely(backend: CanBackend) -> None:
    backend.stop()
    emu = backend.emulator
    for drive in emu.drives:
        assert drive.state in (SOD, FAULT)
        assert drive.nmt_log[-1] == "pre-op"
        tail = [c for c in drive.commands[-20:] if c[2] != FAULT]
        # after the stop: zero torque and quick stop / disable voltage only
        stop_part = [c for c in tail if c[0] in (0x02, 0x00)]
        assert all(torque == 0 for _, torque, _ in stop_part)
    backend.stop()  # idempotent


def test_normal_stop_quick_stops_then_disables(started) -> None:
    backend = started()
    run_ticks(backend, 5, tau=0.3)
    backend.stop()
    for drive in backend.emulator.drives:
        cws = [cw for cw, _, _ in drive.commands]
        last_enabled = max(k for k, cw in enumerate(cws) if cw == 0x0F)
        assert cws[last_enabled + 1 :] and set(cws[last_enabled + 1 :]) <= {0x02, 0x00}
        assert cws[last_enabled + 1] == 0x02 and cws[-1] == 0x00
        assert drive.state == SOD and drive.nmt_log[-1] == "pre-op"
        assert all(t == 0 for _, t, _ in drive.commands[last_enabled + 1 :])


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
            backend.start()
    finally:
        backend.stop()


def test_an_unopenable_bus_is_one_clear_error() -> None:
    cfg = make_cfg("can.emulate=false", "can.hsi.bus.interface=nonexistent_interface")
    backend = make_backend(cfg)
    with pytest.raises(BackendError, match=r"can: hsi bus \(interface=nonexistent_interface"):
        backend.start()
    backend.stop()


def test_registering_the_backend_does_not_import_python_can() -> None:
    code = (
        "import sys; from teleop_rt.hal.base import available_backends; "
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
