"""Found by attacking the command line from outside (session 36): what ``check`` accepts runs,
what ``run`` or a site refuses ``check`` refuses, and a damaged log or an extreme value is one
line, never a traceback."""

from __future__ import annotations

import json

import pytest

from teleop_rt.cli import main
from teleop_rt.recording.reader import read_log
from tests.conftest import CONFIGS
from tests.test_cli import assert_one_error_line
from tests.test_site_logs import rewrite

WALL = str(CONFIGS / "stiff_wall.yaml")


def _run(capsys, *argv: str) -> tuple[int, list[str]]:
    code = main(list(argv))
    return code, capsys.readouterr().err.strip().splitlines()


def test_the_shipped_pose_config_checks_and_runs(tmp_path, capsys) -> None:
    """configs/task_space/ur5_panda_pose.yaml (b per pose component: 6 numbers, a 7-joint TO)
    was refused by check and run alike: the contact warning took b as per joint. That
    joint-space bound is for channel.space: joint only."""
    pose = str(CONFIGS / "task_space" / "ur5_panda_pose.yaml")
    code, err = _run(capsys, "check", pose)
    assert code == 0 and not err, err
    code, err = _run(capsys, "run", pose, "--duration", "0.05", "--no-log", "--json")
    assert code == 0 and not err, err


def test_check_refuses_a_start_outside_the_joint_limits(capsys) -> None:
    """A simulated robot starting outside its joint limits is stopped at the first tick by the
    guard; check says so in one line instead of 'ok'."""
    code, err = _run(capsys, "run", WALL, "--duration", "0.05", "--no-log", "--json",
                     "--set", "hsi.robot.q0_rad=[100, 0]")  # fmt: skip
    assert code == 3
    code, err = _run(capsys, "check", WALL, "--set", "hsi.robot.q0_rad=[100, 0]")
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("teleop-rt: error: hsi.robot.q0_rad: 100 rad for joint 0 (shoulder)")
    assert "outside its limits [-2.6, 2.6] rad" in err[0]
    # without the position limits the guard lets it start: so does check
    code, err = _run(capsys, "check", WALL, "--set", "hsi.robot.q0_rad=[100, 0]",
                     "--set", "safety.position_limits=false")  # fmt: skip
    assert code == 0, err


def test_check_and_run_refuse_a_network_link_without_delay(tmp_path, capsys) -> None:
    """Each site refuses a delay under one tick over Zenoh, after its warm-up; check accepted
    it, and run --link zenoh started both sites to learn it. Both now refuse it at once, in one
    line, and no log is begun."""
    code, err = _run(capsys, "check", WALL, "--set", "link.kind=zenoh")
    assert code == 2 and len(err) == 1 and "channel.delay_ms: a link between processes" in err[0]
    log = tmp_path / "pair.mcap"
    code, err = _run(capsys, "run", WALL, "--link", "zenoh", "--realtime", "--log", str(log))
    assert code == 2 and len(err) == 1 and "channel.delay_ms: a link between processes" in err[0]
    assert not list(tmp_path.glob("pair*"))
    code, err = _run(capsys, "check", WALL, "--set", "link.kind=zenoh",
                     "--set", "channel.delay_ms=2")  # fmt: skip
    assert code == 0, err


@pytest.fixture(scope="module")
def mapped_log(tmp_path_factory: pytest.TempPathFactory):
    """A mapped session's log (schema 3: the map's constants in its ``mapping`` metadata)."""
    path = tmp_path_factory.mktemp("mapped") / "mapped.mcap"
    assert main(["run", str(CONFIGS / "foam.yaml"), "--duration", "0.1", "--json", "--log",
                 str(path), "--set", "mapping.motion_scale=0.5"]) == 0  # fmt: skip
    assert "mapping" in read_log(path).meta
    return path


@pytest.mark.parametrize(
    "value,said",
    [
        ("{not json", "mapping = '{not json' is not a JSON object"),
        ("[1, 2]", "mapping = '[1, 2]' is not a JSON object"),
        ('{"live_inputs": "3"}', "mapping's live_inputs = '\"3\"' is not an integer 0 to 3"),
        ('{"live_inputs": 8}', "mapping's live_inputs = '8' is not an integer 0 to 3"),
        ('{"follows_packets": 1.5}', "mapping's follows_packets = '1.5' is not an integer"),
    ],
)
def test_a_damaged_mapping_metadata_is_one_line(mapped_log, value, said, tmp_path,
                                                capsys) -> None:  # fmt: skip
    """replay of a mapped log whose ``mapping`` metadata is damaged: one line naming it (it was
    a JSONDecodeError or AttributeError traceback); info and metrics do not need it."""
    damaged = tmp_path / "damaged.mcap"
    rewrite(mapped_log, damaged, mapping=value)
    code = main(["replay", str(damaged), "--no-log", "--json"])
    captured = capsys.readouterr()
    assert code == 2, captured.err
    assert_one_error_line(captured.err, str(damaged))
    assert said in captured.err
    for argv in (["info", str(damaged)], ["metrics", str(damaged), "--json"]):
        assert main(argv) == 0
        capsys.readouterr()


def test_the_mapped_log_itself_replays(mapped_log, capsys) -> None:
    code = main(["replay", str(mapped_log), "--no-log", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["replay"]["ticks"] == 100


def test_a_scene_rate_below_one_per_session_logs_the_start_only(tmp_path, capsys) -> None:
    """recording.scene_hz = 1e-300 (accepted: > 0) overflowed the writer's frame selection
    (OverflowError in its process: the log incomplete, exit 4); it is one scene, at the start."""
    log = tmp_path / "scene.mcap"
    code, err = _run(capsys, "run", WALL, "--duration", "0.05", "--json", "--log", str(log),
                     "--set", "recording.scene_hz=1e-300")  # fmt: skip
    assert code == 0 and not err, err
    data = read_log(log)
    assert data.ticks == 50 and not data.truncated
    assert data.other_topics["/tf"][1] == 2  # the static transforms and the first frame


@pytest.mark.parametrize("window", [["--from", "1e308"], ["--from", "1e300", "--to", "1e308"]])
def test_a_window_past_any_log_is_one_line(mapped_log, window, capsys) -> None:
    """--from 1e308 is finite, but its tick is not (OverflowError from math.ceil): it is a
    window after the log's last tick, one line; --to 1e308 is the whole log."""
    image = str(mapped_log.with_suffix(".png"))
    for command in (["metrics", str(mapped_log), "--json"], ["plot", str(mapped_log), "-o", image]):
        code = main([*command, *window])
        err = capsys.readouterr().err
        assert code == 2, err
        assert_one_error_line(err, str(mapped_log))
        assert "holds no ticks (the log's ticks run from 0 to 0.099 s)" in err
    assert main(["metrics", str(mapped_log), "--json", "--to", "1e308"]) == 0
    assert json.loads(capsys.readouterr().out)["ticks"] == 100


@pytest.mark.parametrize("option", ["--env-mass", "--env-damping", "--env-stiffness",
                                    "--amplitude"])  # fmt: skip
def test_bode_refuses_an_infinite_parameter(option, capsys) -> None:
    """An infinite Z_e term (or amplitude) made a NaN model: RuntimeWarnings, NaN figures and
    exit 0. Refused before any work, one line."""
    code = main(["bode", WALL, option, "inf", "--omegas", "1"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert_one_error_line(err, "and finite, got inf")


@pytest.mark.parametrize(
    "config,sets,said",
    [
        ("stiff_wall.yaml", [], "mapping.posture_gain_per_s: the posture task acts in the null "
         "space of the TO's tool Jacobian; it needs channel.space: plane, position or pose"),
        ("task_space/ur5_scara_plane.yaml", [], "mapping.posture_gain_per_s: the TO's 2 joints "
         "have none to spare over the 2 directions of channel.space: plane"),
        ("stiff_wall.yaml", ["channel.space=plane"], "mapping.posture_gain_per_s: the TO's 2 "
         "joints have none to spare"),
    ],
)  # fmt: skip
def test_a_posture_gain_without_a_null_space_is_one_line(config, sets, said, capsys) -> None:
    """A posture gain in joint space, or for a TO with no joint to spare, was taken and did
    nothing (or, at a DLS's damping, leaked); posture_rad there was refused. Both are now."""
    argv = ["check", str(CONFIGS / config), "--set", "mapping.posture_gain_per_s=1"]
    code = main([*argv, *(x for s in sets for x in ("--set", s))])
    err = capsys.readouterr().err
    assert code == 2, err
    assert_one_error_line(err, said)
    assert main(["check", str(CONFIGS / "task_space" / "scara_ur5_plane.yaml"),
                 "--set", "mapping.posture_gain_per_s=1"]) == 0  # fmt: skip


def test_a_rate_too_low_for_the_tos_velocity_loop_is_a_warning(capsys) -> None:
    """At rate_hz = 10 the TO's velocity loop alone is unstable (dt / T2 = 20 >= 2): the contact
    bound is 0, and check and run divided by it (ZeroDivisionError). Now a warning naming it;
    the run ends in a safety stop, as the warning says it would go."""
    sets = ["--set", "rate_hz=10", "--set", "channel.wave_filter_hz=null"]
    code = main(["check", WALL, *sets])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 0 and len(err) == 1, err
    assert err[0] == ("teleop-rt: warning: to joint 0: its velocity loop alone is unstable at "
                      "rate_hz = 10 (dt / T2 = 20 >= 2, T2 = M2/c2; see teleop_rt/analysis/"
                      "contact.py): raise rate_hz or T2")  # fmt: skip
    assert main(["run", WALL, *sets, "--no-log", "--json"]) == 3


def test_a_killed_sites_failure_names_the_signal() -> None:
    """run --link zenoh with a site SIGKILLed mid-run: the table's 'failed:' showed the last
    line of its stderr, Python's resource-tracker warning about the log's shared memory. It is
    the site's own error line if it gave one, else the signal."""
    from teleop_rt.cli_sites import site_failure

    tracker = ("/usr/lib/python3.11/multiprocessing/resource_tracker.py:254: UserWarning: "
               "resource_tracker: There appear to be 1 leaked shared_memory objects to clean "
               "up at shutdown\n"
               "  warnings.warn('resource_tracker: There appear to be %d '\n")  # fmt: skip
    assert site_failure(-9, tracker) == "killed by SIGKILL (exit -9)"
    assert site_failure(-9, "") == "killed by SIGKILL (exit -9)"
    own = "teleop-rt: error: channel.delay_ms: a link between processes needs a delay\n"
    assert site_failure(2, tracker + own) == own.strip()
    assert site_failure(1, "Traceback ...\nRuntimeError: x\n") == "RuntimeError: x"
    assert site_failure(1, "") == "exit 1"


@pytest.mark.parametrize("command", ["run", "site"])
def test_an_empty_log_path_is_refused(command, capsys) -> None:
    """``--log ""`` fell back to the default path (the run wrote a log the user did not name)."""
    argv = [command, WALL, "--log", ""] if command == "run" else [command, "hsi", WALL, "--log", ""]
    with pytest.raises(SystemExit) as ended:
        main(argv)
    err = capsys.readouterr().err
    assert ended.value.code == 2 and "argument --log: an empty path" in err, err
