"""Bad input from the outside (issue 18, "one clear line, never a traceback"): configs and
overrides, damaged logs, empty windows, broken URDFs and early signals. Every case drives the
CLI (``main(argv)`` or a subprocess) and wants exit code 2 and one ``teleop-rt: error:`` line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop_rt.cli import main
from tests.test_cli import assert_one_error_line

ROOT = Path(__file__).resolve().parents[1]
PAPER = str(ROOT / "configs" / "paper_experiment.yaml")


def cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def assert_refused(argv: list[str], capsys: pytest.CaptureFixture[str], *named: str) -> str:
    code, _, err = cli(argv, capsys)
    assert code == 2, err
    assert_one_error_line(err, *named)
    return err


# --- config values ----------------------------------------------------------------------------
@pytest.mark.parametrize("side", ["to", "hsi"])
def test_zero_p_gain_is_refused_naming_the_key(side, capsys) -> None:
    assert_refused(
        ["check", PAPER, "--set", f"{side}.controller.kp=0"], capsys, f"{side}.controller.kp"
    )
    assert_refused(["run", PAPER, "--set", f"{side}.controller.kp=[20, 0]"], capsys, "kp")


def test_zero_kp_of_a_pid_has_no_contact_limit(capsys) -> None:
    """A PID without its P term is a controller (pure I): the P contact analysis sets no limit
    and warns about nothing, even against the stiff wall."""
    sets = ["--set", "to.controller.kind=pid", "--set", "to.controller.kp=0"]
    sets += ["--set", "to.controller.ki=5"]
    code, out, err = cli(["check", str(ROOT / "configs" / "stiff_wall.yaml"), *sets], capsys)
    assert code == 0 and "ok" in out and err == "", err


TICK_COUNTS = [
    "safety.stale_ticks",
    "safety.saturation_stop_ticks",
    "safety.tracking_error_ticks",
    "safety.stop_max_ticks",
]


@pytest.mark.parametrize("key", TICK_COUNTS)
@pytest.mark.parametrize("value", [2**63, 10**8 + 1, 2**70])
def test_tick_counts_have_an_upper_bound(key, value, capsys) -> None:
    assert_refused(["check", PAPER, "--set", f"{key}={value}"], capsys, key, "less than")


def test_a_long_seed_is_refused(capsys) -> None:
    # 5000 digits: more than Python converts; 4000: converted, above the bound
    err = assert_refused(["check", PAPER, "--set", "seed=" + "9" * 5000], capsys, "seed")
    assert len(err) < 300, "the value is not echoed whole"
    assert_refused(["check", PAPER, "--set", "seed=" + "9" * 4000], capsys, "seed", "less than")
    assert_refused(["check", PAPER, "--set", f"seed={2**63}"], capsys, "seed")


def test_a_long_integer_in_a_config_file_is_one_line(tmp_path, capsys) -> None:
    text = Path(PAPER).read_text().replace("../robots", str(ROOT / "robots"))
    path = tmp_path / "seed.yaml"
    assert "\nseed: 0\n" in text  # replaced: a second seed key is refused as a repeated key
    path.write_text(text.replace("\nseed: 0\n", f"\nseed: {'7' * 5000}\n"))
    assert_refused(["check", str(path)], capsys, str(path), "integer too long")


# --- logs -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def real_log(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A real 1.2 s log of the paper experiment (three chunks), as bytes."""
    path = tmp_path_factory.mktemp("log") / "paper.mcap"
    assert main(["run", PAPER, "--duration", "1.2", "--json", "--log", str(path)]) == 0
    return path.read_bytes()


def _damaged(src: bytes, kind: str, where: float | int) -> bytes:
    """``src`` cut at, or with 16 bytes flipped / 256 bytes zeroed from, an offset (a fraction
    of the file, or bytes from its start, or from its end when negative)."""
    n = len(src)
    at = int(where * n) if isinstance(where, float) else where % n
    if kind == "cut":
        return src[:at]
    out = bytearray(src)
    if kind == "flip":
        out[at : at + 16] = bytes(b ^ 0xFF for b in out[at : at + 16])
    else:
        out[at : at + 256] = bytes(len(out[at : at + 256]))
    return bytes(out)


# header, metadata, the attachments, the first chunk's header, every part of the three chunks,
# the summary metadata, the summary section, the footer and the closing magic
SPOTS = [9, 70, 400, 3000, 7000, 7250, 0.05, 0.12, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
SPOTS += [0.95, -1500, -600, -200, -40, -12]
VARIANTS = [("cut", s) for s in SPOTS[1:]] + [("flip", s) for s in SPOTS[:-2]]
VARIANTS += [("zero", s) for s in SPOTS[1:-2:]]


@pytest.mark.parametrize("kind,where", VARIANTS, ids=[f"{k}@{w}" for k, w in VARIANTS])
def test_damaged_logs_work_or_are_one_line(real_log, kind, where, tmp_path, capsys) -> None:
    """replay, metrics (whole and windowed) and plot of a damaged log: each either works or
    says what is wrong in one line with exit code 2."""
    path = tmp_path / "damaged.mcap"
    path.write_bytes(_damaged(real_log, kind, where))
    for argv in (
        ["metrics", str(path)],
        ["metrics", str(path), "--json", "--from", "0.5", "--to", "1.0"],
        ["plot", str(path), "-o", str(tmp_path / "plot.png")],
        ["replay", str(path), "--json", "--no-log"],
    ):
        code, _, err = cli(argv, capsys)
        assert "Traceback" not in err, argv
        if code == 0:
            assert all(line.startswith("teleop-rt: warning: ") for line in err.splitlines()), err
        else:
            assert code == 2, (argv, err)
            assert_one_error_line(err, str(path))


def _chunk_bodies(src: bytes):
    """(offset of the records, their length) of each chunk of an MCAP file, in order."""
    at = 8  # after the magic
    while at + 9 <= len(src):
        op, length = src[at], int.from_bytes(src[at + 1 : at + 9], "little")
        if op == 0x06:  # chunk: start, end, size, crc, compression, records length, records
            n = int.from_bytes(src[at + 9 + 28 : at + 9 + 32], "little")
            records = at + 9 + 32 + n + 8
            yield records, int.from_bytes(src[records - 8 : records], "little")
        at += 9 + length


def test_a_flip_that_still_decompresses_is_caught_by_the_chunk_crc(real_log, tmp_path, capsys):
    """A flipped byte among LZ4's literals decompresses, to wrong values: once it replayed a
    recorded torque of 874 N m into a safety stop (exit 3, no line). The chunk's CRC catches it:
    the ticks before the chunk are read, the damage is named."""
    import lz4.frame

    from teleop_rt.recording.reader import read_log

    records, length = list(_chunk_bodies(real_log))[1]
    clean = lz4.frame.decompress(real_log[records : records + length])
    for at in range(records + length // 2, records + length):  # the first flip that decodes
        damaged = bytearray(real_log)
        damaged[at] ^= 0x10
        try:
            if lz4.frame.decompress(damaged[records : records + length]) != clean:
                break
        except RuntimeError:
            continue
    else:
        pytest.fail("no flip in the chunk decompresses")
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(damaged))
    log = read_log(path)
    assert log.cut_reason is not None and "CRC mismatch" in log.cut_reason, log.cut_reason
    assert 0 < len(log.topics["/hsi"]) < 1200  # the first chunk's ticks, not the rest
    code, _, err = cli(["replay", str(path), "--json", "--no-log"], capsys)
    assert code == 0 and err.startswith("teleop-rt: warning: ") and "gaps" in err, (code, err)


def test_enough_damaged_variants() -> None:
    assert len(VARIANTS) >= 60


def test_replay_of_a_log_cut_before_its_first_tick(real_log, tmp_path, capsys) -> None:
    path = tmp_path / "cut.mcap"
    path.write_bytes(real_log[:50_000])  # inside the first chunk: no tick readable
    for argv in (["replay", str(path), "--no-log"], ["metrics", str(path)], ["plot", str(path)]):
        assert_refused(argv, capsys, "holds no ticks", "file ends at byte 50000")
    assert not path.with_suffix(".png").exists()


@pytest.mark.parametrize(
    "argv, named",
    [
        (["--from", "100"], "the window 100 s to the end holds no ticks"),
        (["--to", "0"], "the window 0 s to 0 s holds no ticks"),
        (["--from", "0.5001", "--to", "0.5009"], "holds no ticks"),  # between two ticks
    ],
)
def test_an_empty_window_is_no_result(real_log, argv, named, tmp_path, capsys) -> None:
    path = tmp_path / "log.mcap"
    path.write_bytes(real_log)
    assert_refused(["metrics", str(path), *argv], capsys, named, "ticks run from 0 to 1.199 s")
    assert_refused(["metrics", str(path), "--json", *argv], capsys, named)
    # plot says the same line as metrics (and docs/logs.md)
    out = str(tmp_path / "p.png")
    assert_refused(["plot", str(path), "-o", out, *argv], capsys, named, "ticks run from 0 to")


def test_a_damaged_attachment_is_named_by_replay(real_log, tmp_path, capsys) -> None:
    """A flipped bit in the config or a URDF attachment (CRC mismatch) would replay another
    session: replay refuses, naming the attachment; metrics and plot do not need them."""
    for needle, name in ((b"duration_s:", "config.yaml"), (b"<robot", "urdf/hsi.urdf")):
        damaged = bytearray(real_log)
        damaged[real_log.index(needle) + 2] ^= 0x20
        path = tmp_path / f"{name.replace('/', '-')}.mcap"
        path.write_bytes(bytes(damaged))
        assert_refused(["replay", str(path), "--no-log"], capsys, name, "damaged")
        assert cli(["metrics", str(path)], capsys)[0] == 0


@pytest.mark.parametrize(
    "text, named",
    [
        ("- 1\n- 2\n", "is not a mapping"),
        ("a: [1,\n", "not valid YAML"),
        ("hsi: x\n", "hsi: Input should be a valid dictionary"),
        ("seed: " + "9" * 5000 + "\n", "integer too long"),
        ("", "the config is empty"),
    ],
    ids=["list", "invalid-yaml", "hsi-x", "long-int", "empty"],
)
def test_replay_of_a_bad_config_attachment(text, named, tmp_path, monkeypatch, capsys) -> None:
    import log_fixtures

    monkeypatch.setattr(log_fixtures, "config_yaml", lambda *args: text)
    log = log_fixtures.write_synthetic_log(tmp_path / "a.mcap", 300)
    assert_refused(["replay", str(log.path), "--no-log"], capsys, "config.yaml attachment", named)


@pytest.mark.parametrize("rate", ["1e-300", "1e300", "inf", "nan", "0", "9" * 5000])
def test_an_impossible_log_rate_is_one_line(rate, tmp_path, capsys) -> None:
    from log_fixtures import write_synthetic_log

    log = write_synthetic_log(tmp_path / "a.mcap", 300, meta={"rate_hz": rate})
    for argv in (["metrics", str(log.path)], ["replay", str(log.path), "--no-log"]):
        err = assert_refused(argv, capsys, "rate_hz", "tick rate")
        assert len(err) < 300


@pytest.mark.parametrize("key", ["delay_ticks", "joints", "env_elements"])
@pytest.mark.parametrize("value", ["x", "-3", "9" * 5000])
def test_bad_integer_metadata_is_one_line(key, value, tmp_path, capsys) -> None:
    from log_fixtures import write_synthetic_log

    log = write_synthetic_log(tmp_path / "a.mcap", 300, meta={key: value})
    assert_refused(["metrics", str(log.path)], capsys, key)


# --- signals before the session runs ----------------------------------------------------------
def _started_loading(pid: int) -> bool:
    """Whether the process has mapped Pinocchio: main() is running and importing the session
    (long before its first tick: the kernels still have to load)."""
    try:
        return "pinocchio" in Path(f"/proc/{pid}/maps").read_text()
    except FileNotFoundError:  # exited
        return True


@pytest.mark.parametrize(
    "sig, code, line",
    [
        (signal.SIGTERM, 143, "teleop-rt: stopped by SIGTERM"),
        (signal.SIGINT, 130, "teleop-rt: interrupted"),
    ],
)
def test_a_signal_while_starting_is_a_clean_exit(sig, code, line) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    argv = [sys.executable, "-m", "teleop_rt.cli", "run", PAPER, "--duration", "60", "--no-log"]
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    try:
        for _ in range(60_000):
            if _started_loading(proc.pid):
                break
            time.sleep(0.001)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == code, err
    assert err == line + "\n" and out == ""  # before the run: no summary


def test_only_the_first_signal_raises() -> None:
    """A second SIGTERM while the first one's exception unwinds (through except and finally
    blocks that close files) does not cut that short; the old handler is back afterwards."""
    from teleop_rt.exit_signals import Terminated, exit_on_signals

    before = signal.getsignal(signal.SIGTERM)
    caught = []
    with exit_on_signals():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # interrupted by the handler's exception
        except Terminated as stop:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.01)  # a second exception would be raised here
            caught.append(stop.exit_code)
    assert caught == [143]
    assert signal.getsignal(signal.SIGTERM) is before


# --- URDFs --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, reason",
    [
        ("<robot name='x'><link name='a'>", "XML mismatched element at line 1"),
        ("not xml", "XML parsing text at line 1"),
        (
            "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'>"
            "<parent link='a'/><child link='b'/></joint></robot>",
            "Joint [j] is of type REVOLUTE but it does not specify limits",
        ),
    ],
    ids=["unclosed", "not-xml", "no-limits"],
)
def test_a_broken_urdf_is_one_line_with_urdfdoms_reason(text, reason, tmp_path) -> None:
    """urdfdom writes its diagnostics to the C-level stderr (fd 2) before Pinocchio raises:
    they become the reason in the one line, not lines of their own (a subprocess sees fd 2)."""
    urdf = tmp_path / "broken.urdf"
    urdf.write_text(text)
    argv = [sys.executable, "-m", "teleop_rt.cli", "check", PAPER, "--set", f"to.robot.urdf={urdf}"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    done = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2, done.stderr
    assert_one_error_line(done.stderr, "to.robot.urdf", "broken.urdf is not a valid URDF", reason)


# --- issue 29: accepted though wrong ----------------------------------------------------------
def _paper_copy(tmp_path: Path, extra: str = "", name: str = "paper.yaml") -> Path:
    """The paper experiment's config with its URDFs pointed back to robots/ and ``extra``."""
    text = Path(PAPER).read_text().replace("../robots", str(ROOT / "robots"))
    path = tmp_path / name
    path.write_text(text + extra)
    return path


@pytest.mark.parametrize(
    "key", ["link.peer_timeout_ms", "link.handshake_timeout_s", "recording.ring_s", "seed"]
)
@pytest.mark.parametrize("word", ["true", "yes", "off"])
def test_a_boolean_for_a_number_is_refused(key, word, capsys) -> None:
    assert_refused(
        ["check", PAPER, "--set", f"{key}={word}"], capsys, key, "expected a number, got"
    )


def test_a_boolean_in_a_per_joint_list_is_refused(capsys) -> None:
    assert_refused(["check", PAPER, "--set", "to.controller.kp=[20, true]"], capsys,
                   "to.controller.kp.1: expected a number, got true")  # fmt: skip


def test_a_boolean_for_a_number_in_a_config_file_is_refused(tmp_path, capsys) -> None:
    path = _paper_copy(tmp_path, "\nlink:\n  peer_timeout_ms: true\n")
    assert_refused(["check", str(path)], capsys, "link.peer_timeout_ms: expected a number")


def _numeric_fields(cls, seen: set) -> list[tuple[type, str]]:
    """Every (section class, field) of the schema whose annotation holds an int or a float and
    no bool, walking the nested sections."""
    import typing

    from pydantic import BaseModel

    from teleop_rt.schema import annotation_leaves

    out = []
    if cls in seen:
        return out
    seen.add(cls)
    for name, field in cls.model_fields.items():
        leaves = annotation_leaves(field.annotation)
        for leaf in leaves:
            sections = [leaf] + [a for a in typing.get_args(leaf) if isinstance(a, type)]
            for sub in sections:
                if isinstance(sub, type) and issubclass(sub, BaseModel):
                    out += _numeric_fields(sub, seen)
        if bool not in leaves and any(leaf in (int, float) for leaf in leaves):
            out.append((cls, name))
    return out


def test_every_numeric_field_of_the_schema_refuses_booleans() -> None:
    """Not a list to keep up to date: every section's every number (config, impairment, can)."""
    from pydantic import ValidationError

    from teleop_rt.config import SessionConfig
    from teleop_rt.schema import BOOL_ERROR

    fields = _numeric_fields(SessionConfig, set())
    assert len(fields) > 60 and {c.__name__ for c, _ in fields} >= {
        "LinkSpec", "RecordingSpec", "ImpairmentSpec", "DriveSpec", "ZenohEndpoints",
    }  # fmt: skip
    for cls, name in fields:
        with pytest.raises(ValidationError) as info:
            cls.model_validate({name: True})
        first = info.value.errors()[0]
        assert first["type"] == BOOL_ERROR and first["ctx"]["key"] == name, (cls, name)


def test_a_repeated_key_in_a_config_file_is_refused(tmp_path, capsys) -> None:
    path = _paper_copy(tmp_path, "\nchannel:\n  delay_ms: 50\n")
    err = assert_refused(["check", str(path)], capsys, str(path), "duplicate key 'channel'")
    first = Path(PAPER).read_text().splitlines().index("channel:") + 1
    assert f"lines {first} and " in err
    path = _paper_copy(tmp_path, "\nseed: 1\nseed: 2\n", "seed.yaml")
    assert_refused(["check", str(path)], capsys, "duplicate key 'seed'")
    assert_refused(["check", PAPER, "--set", "channel={delay_ms: 1, delay_ms: 2}"], capsys,
                   "--set channel", "duplicate key 'delay_ms'")  # fmt: skip


def test_torque_limits_off_unquoted_means_off(tmp_path, capsys) -> None:
    """YAML 1.1 reads an unquoted off as false; for torque_limits it means the choice 'off'."""
    path = _paper_copy(tmp_path, "\nsafety:\n  torque_limits: off\n")
    for argv in (["check", str(path), "--print"],
                 ["check", PAPER, "--print", "--set", "safety.torque_limits=off"]):  # fmt: skip
        code, out, err = cli(argv, capsys)
        assert code == 0, err
        assert "torque_limits: 'off'" in out


@pytest.mark.parametrize("value", ["on", "yes", "true"])
def test_a_word_read_as_a_boolean_is_refused_with_a_hint(value, capsys) -> None:
    for key in ("safety.torque_limits", "recording.on_loss"):
        assert_refused(["check", PAPER, "--set", f"{key}={value}"], capsys, key,
                       "got the boolean true", "expected one of")  # fmt: skip


@pytest.mark.parametrize("key", ["hsi.robot.urdf", "to.robot", "hsi"])
def test_replay_refuses_a_new_robot_model(real_log, key, tmp_path, capsys) -> None:
    """A replay re-runs the robots attached to the log: a --set that changes a robot's model
    would be shown in the title and ignored; it is refused."""
    path = tmp_path / "log.mcap"
    path.write_bytes(real_log)
    value = {"hsi.robot.urdf": str(tmp_path / "other.urdf"),
             "to.robot": "{example_robot: double_pendulum}",
             "hsi": "{robot: {example_robot: double_pendulum}}"}[key]  # fmt: skip
    assert_refused(["replay", str(path), "--no-log", "--set", f"{key}={value}"], capsys,
                   f"--set {key}: a replay re-runs the logged robots")  # fmt: skip


# --- issue 29: files that are not regular files, too long names, too much work -----------------
LONG = "a" * 300


@pytest.mark.parametrize(
    "path, named",
    [
        ("/dev/zero", "is a character device, not a regular file"),
        ("/tmp", "is a folder, not a regular file"),
        (f"/tmp/{LONG}.yaml", "cannot be read (File name too long)"),
    ],
    ids=["device", "folder", "long-name"],
)
def test_a_config_that_is_no_regular_file_is_one_line(path, named, capsys) -> None:
    err = assert_refused(["check", path], capsys, named)
    assert len(err) < 300


def test_a_fifo_is_refused_without_blocking(tmp_path) -> None:
    """A FIFO as a config, URDF, trace or log: refused in one line without being opened (an
    open for reading blocks until a writer comes)."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    delay = ["--set", "channel.delay_ms=10"]
    for argv, named in (
        (["check", str(fifo)], "config"),
        (["check", PAPER, "--set", f"to.robot.urdf={fifo}"], "to.robot.urdf"),
        (["check", PAPER, *delay, "--set", f"link.impairment.trace={fifo}"], "impairment trace"),
        (["info", str(fifo)], str(fifo)),
        (["metrics", str(fifo)], str(fifo)),
        (["replay", str(fifo), "--no-log"], str(fifo)),
        (["plot", str(fifo), "-o", str(tmp_path / "p.png")], str(fifo)),
    ):
        done = subprocess.run([sys.executable, "-m", "teleop_rt.cli", *argv], env=env,
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert done.returncode == 2, (argv, done.stderr)
        assert_one_error_line(done.stderr, named, "is a FIFO (named pipe), not a regular file")


def test_dev_zero_as_a_trace_or_urdf_is_one_line(capsys) -> None:
    """Read whole before its size was checked: a MemoryError (or the OOM killer)."""
    assert_refused(["check", PAPER, "--set", "channel.delay_ms=10", "--set",
                    "link.impairment.trace=/dev/zero"], capsys,
                   "impairment trace /dev/zero: is a character device")  # fmt: skip
    assert_refused(["check", PAPER, "--set", "to.robot.urdf=/dev/zero"], capsys,
                   "to.robot.urdf: /dev/zero: is a character device")  # fmt: skip


def test_a_large_trace_is_refused_before_it_is_read(tmp_path, capsys) -> None:
    from teleop_rt.com.impairment import MAX_TRACE_BYTES

    trace = tmp_path / "big.csv"
    with open(trace, "wb") as f:  # sparse: no disk space
        f.truncate(MAX_TRACE_BYTES + 1)
    assert_refused(["check", PAPER, "--set", "channel.delay_ms=10", "--set",
                    f"link.impairment.trace={trace}"], capsys,
                   f"larger than {MAX_TRACE_BYTES} bytes")  # fmt: skip


@pytest.mark.parametrize("command", ["metrics", "info", "plot", "replay"])
def test_a_long_file_name_is_one_line(command, tmp_path, capsys) -> None:
    log = f"/tmp/{LONG}.mcap"
    err = assert_refused([command, log], capsys, "(File name too long)")
    assert len(err) < 300
    urdf = f"/tmp/{LONG}.urdf"
    assert_refused(["check", PAPER, "--set", f"to.robot.urdf={urdf}"], capsys,
                   "to.robot.urdf", "File name too long")  # fmt: skip


@pytest.mark.parametrize("omega", ["1e-9", "0.01"])
def test_bode_refuses_a_frequency_too_low_to_measure(omega, capsys) -> None:
    """1e-9 rad/s asked for windows of 45.7 TiB; refused before any work, naming it."""
    assert_refused(["bode", PAPER, "--omegas", f"2,{omega}"], capsys,
                   f"frequency {float(omega):g} rad/s", "limit of 3600 s")  # fmt: skip
    assert_refused(["bode", PAPER, "--max-seconds", "1e9"], capsys, "--max-seconds", "3600")


# --- issue 28's texts -------------------------------------------------------------------------
def test_the_contact_warning_states_the_right_fraction(capsys) -> None:
    """500 kN/m is 68 321 N m/rad at q0 against a limit of 36 000: 190 %, beyond the limit."""
    code, _, err = cli(["check", PAPER, "--set", "environment.1.stiffness_n_per_m=500000"], capsys)
    assert code == 0
    line = next(x for x in err.splitlines() if "environment.1" in x)
    assert "68321 N m/rad" in line and "190% of the sampled contact loop's limit 36000" in line
    assert "beyond it the contact is unstable" in line and "above 50% of" not in line


@pytest.mark.parametrize(
    "typed, suggestion",
    [("channel.dleay_ms", "did you mean 'delay_ms'?"), ("operatr", "did you mean 'operator'?"),
     ("link.peer_timout_ms", "did you mean 'peer_timeout_ms'?"), ("channel.xyz", None),
     ("seed_value_of_it", None)],
)  # fmt: skip
def test_an_unknown_key_suggests_only_a_close_one(typed, suggestion, capsys) -> None:
    err = assert_refused(["check", PAPER, "--set", f"{typed}=3"], capsys, f"{typed}: unknown key")
    if suggestion is None:
        assert "did you mean" not in err
    else:
        assert suggestion in err


def test_version_is_the_logs_version(capsys) -> None:
    from teleop_rt.version import software_version

    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out == f"teleop-rt {software_version()}\n"


def test_help_texts(capsys) -> None:
    def help_of(*argv: str) -> str:
        with pytest.raises(SystemExit):
            main([*argv, "--help"])
        return " ".join(capsys.readouterr().out.split())

    bode = help_of("bode", PAPER)
    assert "(default 0)" not in bode and "the config's environment" in bode
    assert "(default 60, at most 3600)" in bode
    assert "site" in help_of("replay", "x") and "site" in help_of("info", "x")
    site = help_of("site", "hsi", PAPER)
    assert "--backend NAME" in site and "hsi:|to:" not in site


def test_a_fast_runs_preempted_max_is_explained() -> None:
    """Fast mode's max tick of 12-24 ms (the host preempted the process) gets a note; a max
    near p99 none."""
    from teleop_rt.report import preemption_note

    note = preemption_note({"p50": 20.0, "p99": 40.0, "p99.9": 900.0, "max": 24_000.0})
    assert note is not None and "host preemption" in note and "24 ms" in note
    assert preemption_note({"p50": 20.0, "p99": 40.0, "p99.9": 60.0, "max": 90.0}) is None


@pytest.mark.parametrize("tool", ["bench_instructions", "bench_link"])
def test_a_tools_help_is_not_cut_mid_sentence(tool) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    done = subprocess.run([sys.executable, str(ROOT / "tools" / f"{tool}.py"), "--help"],
                          capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    description = " ".join(done.stdout.split("\n\n")[1].split())
    assert description.endswith((".", ")")), description
    assert {"bench_instructions": "instruction counts repeat).",
            "bench_link": "the same config in one process."}[tool] in description  # fmt: skip


def test_log_on_a_folder_says_it_is_a_folder(tmp_path, capsys) -> None:
    assert_refused(["run", PAPER, "--duration", "0.01", "--log", str(tmp_path)], capsys,
                   f"--log {tmp_path}: is a folder")  # fmt: skip
