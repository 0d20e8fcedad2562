"""The strict session config: shipped configs load, overrides work, and every class of mistake
ends as one ``ConfigError`` line that names the offending key.

Broken configs are built from ``configs/paper_experiment.yaml`` (read with ``read_yaml``, one
value changed, validated with ``from_dict``) or written as YAML files to tmp_path.
"""

from __future__ import annotations

import copy
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from teleop_rt.config import (
    SessionConfig,
    apply_overrides,
    from_dict,
    load,
    per_joint,
    read_yaml,
)
from teleop_rt.errors import ConfigError, TeleopError
from teleop_rt.session import Session

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
PAPER = CONFIGS / "paper_experiment.yaml"
SHIPPED = sorted(CONFIGS.glob("*.yaml"))

Mutation = Callable[[dict[str, Any]], None]


@pytest.fixture(scope="module")
def paper_data() -> dict[str, Any]:
    return read_yaml(PAPER)


def build(paper_data: dict[str, Any], mutate: Mutation) -> SessionConfig:
    data = copy.deepcopy(paper_data)
    mutate(data)
    return from_dict(data, base_dir=CONFIGS)


def assert_names_key(err: BaseException, key: str) -> None:
    """The message is one line and names ``key`` as a whole dotted key (not a prefix of a
    longer path such as ``hsi.virtual_mass.constrained-float``)."""
    msg = str(err)
    assert isinstance(err, ConfigError), f"{type(err).__name__}: {msg}"
    assert "\n" not in msg, f"more than one line: {msg!r}"
    assert re.search(rf"(^|\s){re.escape(key)}(:|\s|$)", msg), f"{key!r} not named in {msg!r}"


def config_error(paper_data: dict[str, Any], mutate: Mutation) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        build(paper_data, mutate)
    return info.value


def session_error(paper_data: dict[str, Any], mutate: Mutation) -> ConfigError:
    """Errors that need the robot models: the config validates, building the session fails."""
    cfg = build(paper_data, mutate)
    with pytest.raises(ConfigError) as info:
        Session(cfg)
    return info.value


def setter(path: str, value: Any) -> Mutation:
    """A mutation setting data[a][b]... (list indices as integers) to value."""

    def mutate(data: dict[str, Any]) -> None:
        *parents, last = [int(p) if p.isdigit() else p for p in path.split(".")]
        node: Any = data
        for p in parents:
            node = node[p]
        node[last] = value

    return mutate


# --- shipped configs ---------------------------------------------------------------------------
def test_the_shipped_configs_are_all_found() -> None:
    assert {p.name for p in SHIPPED} >= {
        "free_space.yaml",
        "foam.yaml",
        "stiff_wall.yaml",
        "paper_experiment.yaml",
    }


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_config_loads(path: Path) -> None:
    cfg = load(path)
    assert isinstance(cfg, SessionConfig)
    assert cfg.name == path.stem
    assert cfg.n_ticks == round(cfg.duration_s * cfg.rate_hz) > 0
    for side in (cfg.hsi, cfg.to):
        # relative URDF paths are resolved against the config's directory, not the cwd
        assert side.robot.urdf is not None and side.robot.urdf.is_absolute()
        assert side.robot.urdf.is_file()


def test_loading_does_not_depend_on_the_working_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    cfg = load(os.path.relpath(PAPER, tmp_path))
    assert cfg.hsi.robot.urdf == (ROOT / "robots" / "urdf" / "scara_2dof.urdf").resolve()


def test_the_paper_config_has_the_papers_parameters() -> None:
    cfg = load(PAPER)
    assert cfg.dt == pytest.approx(1e-3)
    assert cfg.delay_ticks == 0
    assert cfg.hsi.virtual_mass == 0.1 and cfg.to.virtual_mass == 0.1
    assert (cfg.hsi.controller.kind, cfg.hsi.controller.kp) == ("p", 2.0)
    assert (cfg.to.controller.kind, cfg.to.controller.kp) == ("p", 20.0)
    assert [e.kind for e in cfg.environment] == ["foam", "wall"]


# --- overrides ---------------------------------------------------------------------------------
def test_override_a_scalar_and_a_new_section(paper_data: dict[str, Any]) -> None:
    data = copy.deepcopy(paper_data)
    del data["plant"]
    out = apply_overrides(data, ["channel.delay_ms=50", "plant.substeps=4", "name=x"])
    assert out is data
    cfg = from_dict(data, base_dir=CONFIGS)
    assert cfg.channel.delay_ms == 50 and cfg.delay_ticks == 50
    assert cfg.plant.substeps == 4
    assert cfg.name == "x"


def test_override_list_item_by_index(paper_data: dict[str, Any]) -> None:
    data = apply_overrides(copy.deepcopy(paper_data), ["environment.0.stiffness_n_per_m=100"])
    cfg = from_dict(data, base_dir=CONFIGS)
    assert cfg.environment[0].stiffness_n_per_m == 100
    assert cfg.environment[1].stiffness_n_per_m == 5000  # the other item is untouched


def test_override_value_is_parsed_as_yaml(paper_data: dict[str, Any]) -> None:
    data = apply_overrides(
        copy.deepcopy(paper_data),
        [
            "hsi.virtual_mass=[0.2, 0.3]",
            "channel.wave_filter_hz=null",
            "to.compensate_friction=false",
        ],
    )
    cfg = from_dict(data, base_dir=CONFIGS)
    assert cfg.hsi.virtual_mass == [0.2, 0.3]
    assert cfg.channel.wave_filter_hz is None
    assert cfg.to.compensate_friction is False


def test_load_applies_overrides_before_validation() -> None:
    cfg = load(PAPER, ["channel.delay_ms=20", "environment.1.stiffness_n_per_m=2000"])
    assert cfg.delay_ticks == 20
    assert cfg.environment[1].stiffness_n_per_m == 2000
    with pytest.raises(ConfigError) as info:
        load(PAPER, ["channel.delay_ms=0.5"])
    assert_names_key(info.value, "channel.delay_ms")


@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("channel.delay_ms", "channel.delay_ms"),  # no '='
        ("=5", "'=5'"),  # no key
        ("environment.9.stiffness_n_per_m=1", "environment.9"),  # index out of range
        ("environment.first.stiffness_n_per_m=1", "environment.first"),  # not an index
        ("environment.-1.stiffness_n_per_m=1", "environment.-1"),  # negative index
        ("environment.\u00b2.stiffness_n_per_m=1", "environment.\u00b2"),  # a digit, not decimal
        ("hsi.virtual_mass.0=1", "hsi.virtual_mass"),  # a number is not a section
        ("channel.delay_ms=[1, 2", "channel.delay_ms"),  # value is not valid YAML
        ("name=" + "[" * 600, "name"),  # value nested too deeply to parse
    ],
)
def test_bad_override_syntax(paper_data: dict[str, Any], override: str, named: str) -> None:
    with pytest.raises(ConfigError) as info:
        apply_overrides(copy.deepcopy(paper_data), [override])
    msg = str(info.value)
    assert msg.startswith("--set ") and "\n" not in msg
    assert named in msg


def test_override_with_unknown_key_is_named_by_validation(paper_data: dict[str, Any]) -> None:
    data = apply_overrides(copy.deepcopy(paper_data), ["channel.dealy_ms=5"])
    with pytest.raises(ConfigError) as info:
        from_dict(data, base_dir=CONFIGS)
    assert_names_key(info.value, "channel.dealy_ms")


# --- one test per class of mistake ------------------------------------------------------------
@pytest.mark.parametrize(
    "key",
    [
        "colour",
        "hsi.mass",
        "hsi.controller.gain",
        "channel.dealy_ms",
        "environment.0.colour",
        "operator.waypoints.1.speed",
    ],
)
def test_unknown_key(paper_data: dict[str, Any], key: str) -> None:
    err = config_error(paper_data, setter(key, 1))
    assert_names_key(err, key)
    assert "unknown key" in str(err)


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("rate_hz", "fast", "rate_hz"),
        ("rate_hz", 1000.5, "rate_hz"),
        ("plant.substeps", 2.5, "plant.substeps"),
        ("name", ["a"], "name"),
        ("hsi.virtual_mass", "heavy", "hsi.virtual_mass"),
        ("hsi.virtual_mass", [0.1, "x"], "hsi.virtual_mass.1"),
        ("to.controller.output_limit", {"max": 1}, "to.controller.output_limit"),
        ("hsi.robot.q0_rad", "zero", "hsi.robot.q0_rad"),
        ("environment.0.normal", "up", "environment.0.normal"),
        ("operator.stiffness_n_per_m", [300], "operator.stiffness_n_per_m"),
        ("duration_s", float("nan"), "duration_s"),
        ("hsi", None, "hsi"),
    ],
)
def test_wrong_type(paper_data: dict[str, Any], key: str, value: Any, named: str) -> None:
    assert_names_key(config_error(paper_data, setter(key, value)), named)


@pytest.mark.parametrize(
    ("value", "named"),
    [(0, "hsi.virtual_mass"), (-0.1, "hsi.virtual_mass"), ([0.1, 0.0], "hsi.virtual_mass.1")],
)
def test_virtual_mass_must_be_positive(paper_data: dict[str, Any], value: Any, named: str) -> None:
    err = config_error(paper_data, setter("hsi.virtual_mass", value))
    assert_names_key(err, named)
    assert "greater than 0" in str(err)


@pytest.mark.parametrize("value", [0, -2.0, [2.0, 0.0]])
def test_wave_impedance_must_be_positive(paper_data: dict[str, Any], value: Any) -> None:
    err = config_error(paper_data, setter("channel.wave_impedance", value))
    assert_names_key(
        err, "channel.wave_impedance.1" if isinstance(value, list) else "channel.wave_impedance"
    )


@pytest.mark.parametrize("gain", ["ki", "kd"])
def test_p_controller_takes_no_ki_or_kd(paper_data: dict[str, Any], gain: str) -> None:
    err = config_error(paper_data, setter(f"hsi.controller.{gain}", 0.5))
    assert_names_key(err, "hsi.controller")
    assert "kind" in str(err)
    # the same gains are fine for a PID controller, and a zero ki is fine for P
    cfg = build(paper_data, lambda d: d["hsi"]["controller"].update(kind="pid", **{gain: 0.5}))
    assert getattr(cfg.hsi.controller, gain) == 0.5
    assert build(paper_data, setter(f"hsi.controller.{gain}", 0.0)).hsi.controller.kind == "p"


@pytest.mark.parametrize(("delay_ms", "rate_hz"), [(1.5, 1000), (0.25, 2000), (5, 300)])
def test_delay_must_be_whole_ticks(
    paper_data: dict[str, Any], delay_ms: float, rate_hz: int
) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["channel"]["delay_ms"] = delay_ms
        d["rate_hz"] = rate_hz

    err = config_error(paper_data, mutate)
    assert_names_key(err, "channel.delay_ms")
    assert "whole number" in str(err)


@pytest.mark.parametrize(
    ("delay_ms", "rate_hz", "ticks"), [(1.5, 2000, 3), (50, 1000, 50), (0, 1000, 0)]
)
def test_whole_tick_delays_are_accepted(
    paper_data: dict[str, Any], delay_ms: float, rate_hz: int, ticks: int
) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["channel"]["delay_ms"] = delay_ms
        d["rate_hz"] = rate_hz

    assert build(paper_data, mutate).delay_ticks == ticks


@pytest.mark.parametrize("duration_s", [1e-4, 1e12, 1e308])
def test_duration_must_give_a_sane_number_of_ticks(
    paper_data: dict[str, Any], duration_s: float
) -> None:
    # shorter than one tick runs nothing; absurdly long ones overflowed or asked for petabytes
    assert_names_key(config_error(paper_data, setter("duration_s", duration_s)), "duration_s")


def test_missing_urdf_file_is_named_when_the_session_is_built(paper_data: dict[str, Any]) -> None:
    cfg = build(paper_data, setter("hsi.robot.urdf", "../robots/urdf/no_such_robot.urdf"))
    assert cfg.hsi.robot.urdf == CONFIGS.parent / "robots" / "urdf" / "no_such_robot.urdf"
    with pytest.raises(ConfigError) as info:
        Session(cfg)
    assert_names_key(info.value, "hsi.robot.urdf")
    assert "no_such_robot.urdf" in str(info.value)


def test_invalid_urdf_file_is_named(paper_data: dict[str, Any], tmp_path: Path) -> None:
    bad = tmp_path / "broken.urdf"
    bad.write_text("<robot name='x'><link name='a'>")
    err = session_error(paper_data, setter("to.robot.urdf", str(bad)))
    assert_names_key(err, "to.robot.urdf")


@pytest.mark.parametrize(
    "key", ["hsi.virtual_mass", "to.virtual_mass", "channel.wave_impedance", "to.controller.kp"]
)
def test_per_joint_list_longer_than_the_robot(paper_data: dict[str, Any], key: str) -> None:
    err = session_error(paper_data, setter(key, [1.0, 1.0, 1.0]))
    assert_names_key(err, key)
    assert "3 entries" in str(err) and "2 joints" in str(err)


def test_per_joint_broadcasts_and_checks_length() -> None:
    assert per_joint(0.5, 3, "k") == [0.5, 0.5, 0.5]
    assert per_joint([1, 2], 2, "k") == [1.0, 2.0]
    assert per_joint(None, 2, "k") is None
    with pytest.raises(ConfigError) as info:
        per_joint([1.0], 2, "hsi.controller.kd")
    assert_names_key(info.value, "hsi.controller.kd")


def test_robot_needs_exactly_one_source(paper_data: dict[str, Any]) -> None:
    err = config_error(paper_data, setter("hsi.robot.example_robot", "double_pendulum"))
    assert_names_key(err, "hsi.robot")
    assert "exactly one" in str(err)
    err = config_error(paper_data, lambda d: d["to"]["robot"].pop("urdf"))
    assert_names_key(err, "to.robot")


def test_unknown_example_robot_is_named(paper_data: dict[str, Any]) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["hsi"]["robot"] = {"example_robot": "no_such_robot_xyz", "ee_frame": "tool"}

    err = session_error(paper_data, mutate)
    assert_names_key(err, "hsi.robot.example_robot")
    assert "no_such_robot_xyz" in str(err)


@pytest.mark.parametrize("times", [[1.5, 1.5, 5.0], [3.0, 2.0, 5.0], [0.0, 1.0, 2.0]])
def test_waypoint_times_must_increase(paper_data: dict[str, Any], times: list[float]) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["operator"]["waypoints"] = [{"t_s": t, "position_m": [0.3, 0.0]} for t in times]

    err = config_error(paper_data, mutate)
    assert_names_key(err, "operator.waypoints")
    assert "increasing" in str(err)


@pytest.mark.parametrize("normal", [[0, 0], [0.0, 0.0, 0.0]])
def test_zero_normal_vector(paper_data: dict[str, Any], normal: list[float]) -> None:
    err = config_error(paper_data, setter("environment.1.normal", normal))
    assert_names_key(err, "environment.1.normal")
    assert "zero vector" in str(err)


def test_unknown_environment_kind(paper_data: dict[str, Any]) -> None:
    assert_names_key(
        config_error(paper_data, setter("environment.0.kind", "lava")), "environment.0"
    )


def test_a_missing_required_section_is_named(paper_data: dict[str, Any]) -> None:
    assert_names_key(config_error(paper_data, lambda d: d.pop("operator")), "operator")


# --- the file itself ---------------------------------------------------------------------------
def write(tmp_path: Path, text: str, name: str = "session.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_nonexistent_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such config file"):
        load(tmp_path / "missing.yaml")


@pytest.mark.parametrize("text", ["", "\n", "# only a comment\n", "---\n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    with pytest.raises(ConfigError) as info:
        load(write(tmp_path, text))
    assert "empty" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("text", ["- name: a\n- name: b\n", "just a string\n", "42\n"])
def test_top_level_must_be_a_mapping(tmp_path: Path, text: str) -> None:
    with pytest.raises(ConfigError, match="mapping at the top level"):
        load(write(tmp_path, text))
    with pytest.raises(ConfigError, match="mapping at the top level"):
        load(write(tmp_path, text), ["name=x"])


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("name: a\nhsi: [1, 2\n", None),
        ("name: a\n  rate_hz: 1000\n", "line 2"),
        ("name:\n\t- x\n", "line 2"),
    ],
)
def test_invalid_yaml_syntax(tmp_path: Path, text: str, line: str | None) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: not valid YAML") and "\n" not in msg
    if line:
        assert line in msg


def test_python_object_tags_are_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "name: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load(path)


def test_deeply_nested_yaml_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load(write(tmp_path, "name: " + "[" * 600 + "\n"))
    assert "\n" not in str(info.value)


def test_yaml_alias_bomb_is_refused_at_the_first_alias(tmp_path: Path) -> None:
    # "billion laughs": 9 levels of 9 references, 9**9 strings if expanded. The loader must stop
    # at the first alias (line 2) instead of building or expanding anything.
    lines = ['l0: &l0 "lol"']
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 10)]
    path = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(ConfigError) as info:
        load(path)
    msg = str(info.value)
    assert "aliases" in msg and "*l0" in msg and "line 2" in msg
    assert "\n" not in msg


def test_anchors_and_merge_keys_are_refused_too(tmp_path: Path) -> None:
    text = "base: &b {kind: p, kp: 2.0}\nother: {<<: *b}\n"
    with pytest.raises(ConfigError, match="aliases"):
        read_yaml(write(tmp_path, text))


def test_oversized_file_is_refused_before_parsing(tmp_path: Path) -> None:
    path = write(tmp_path, "# " + "x" * 1_000_001 + "\n")
    with pytest.raises(ConfigError, match="larger than"):
        read_yaml(path)


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a folder, not a regular file"):
        load(tmp_path)


def test_config_error_is_a_teleop_error_with_exit_code_2() -> None:
    assert issubclass(ConfigError, TeleopError)
    assert ConfigError.exit_code == 2


def test_a_yaml_file_written_by_hand_round_trips(tmp_path: Path) -> None:
    text = PAPER.read_text().replace("delay_ms: 0", "delay_ms: 100")
    # relative URDF paths resolve against the copy's directory: point them back to the robots
    text = text.replace("../robots", str(ROOT / "robots"))
    cfg = load(write(tmp_path, text))
    assert cfg.delay_ticks == 100
    assert cfg.hsi.robot.urdf is not None and cfg.hsi.robot.urdf.is_file()


def test_cartesian_loads_need_a_named_tool_frame(paper_data: dict[str, Any]) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["hsi"]["robot"] = {"example_robot": "double_pendulum"}  # its last frame is the elbow

    assert_names_key(config_error(paper_data, mutate), "hsi.robot.ee_frame")


@pytest.mark.parametrize("delay", [1e7, 10001.0])
def test_delay_is_bounded(paper_data: dict[str, Any], delay: float) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["channel"]["delay_ms"] = delay

    assert_names_key(config_error(paper_data, mutate), "channel.delay_ms")


def test_session_name_cannot_escape_the_log_folder(paper_data: dict[str, Any]) -> None:
    def mutate(d: dict[str, Any]) -> None:
        d["name"] = "../../escaped"

    assert_names_key(config_error(paper_data, mutate), "name")
