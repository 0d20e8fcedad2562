"""Replay: re-simulate a logged session, driven by the logged operator input, tick-locked.

The session is rebuilt from the config stored in the log (``--set`` overrides applied on top,
so a replay can answer "what would this operator motion have felt like with 100 ms of delay?").
The operator is the logged one:

* a scripted hand: its logged reference (position and velocity at every tick) drives the same
  hand spring-damper; with no overrides (and one sub-step per tick) the replay reproduces every
  logged signal bit for bit;
* the paper's damper operator: it is passive and has no input; the config's damper is used;
* no operator model (a real person on hardware): the logged HSI tool motion becomes the hand's
  reference (forward kinematics of the logged joint angles, velocity by central differences).

A replay always runs on the simulated backend. The operator's live inputs (a CAN drive's
clutch and presence bits, the terminal's keys: ``teleop_rt.keys``) are the logged ones: each
tick's ``inputs`` in /hsi, read by a map set up as the log's ``mapping`` metadata says
(``take_logged_inputs``), so a session with a live clutch replays bit for bit too.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from teleop_rt.config import SessionConfig, apply_overrides, from_dict
from teleop_rt.errors import ConfigError, quote
from teleop_rt.hal.signals import INPUT_CLUTCH, INPUT_PRESENT
from teleop_rt.model import RobotModel
from teleop_rt.recording.reader import LogData, LogError, read_log, require_ticks
from teleop_rt.session import Session
from teleop_rt.world import LoggedTrajectory, ScriptedHand

if TYPE_CHECKING:
    from teleop_rt.site import Site

# hand used for logs without an operator model (a person's motion imposed through a stiff grip)
PERSON_HAND_STIFFNESS_N_PER_M = 2000.0
PERSON_HAND_DAMPING_N_S_PER_M = 40.0


def replay_config(data: LogData, overrides: list[str]) -> SessionConfig:
    """The logged session's config with overrides, on the simulated backend."""
    raw = data.raw_config()
    if raw is None:
        raise LogError(f"{data.path}: the log holds no config.yaml attachment; cannot replay")
    data.config()  # the attachment alone first: its errors name it, not --set
    raw["backend"] = "sim"
    for side in ("hsi", "to"):  # a robot's own backend too (a CAN robot replays simulated)
        if isinstance(raw.get(side), dict):
            raw[side].pop("backend", None)
    logged = {side: _model_source(raw, side) for side in ("hsi", "to")}
    raw = apply_overrides(raw, overrides)
    for side in ("hsi", "to"):
        now = _model_source(raw, side)
        if now is not None and now != logged[side]:
            raise ConfigError(
                f"--set {_override_of(overrides, side)}: a replay re-runs the logged robots (the "
                "URDFs attached to the log) and cannot change a robot's model; run the config "
                "with the other robot instead"
            )
    _restore_urdfs(raw, data)
    return from_dict(raw)


_MODEL_KEYS = ("urdf", "example_robot")  # what a robot's model is loaded from


def _model_source(raw: dict, side: str) -> tuple | None:
    """Where ``side``'s robot model comes from in a raw config (None where --set made it
    something that is not a section: from_dict says what is wrong with that)."""
    robot = raw.get(side)
    robot = robot.get("robot") if isinstance(robot, dict) else None
    return tuple(robot.get(k) for k in _MODEL_KEYS) if isinstance(robot, dict) else None


def _override_of(overrides: list[str], side: str) -> str:
    """The --set key that changed ``side``'s model (it, or a section holding it)."""
    targets = [f"{side}.robot.{k}" for k in _MODEL_KEYS]
    for item in overrides:
        key = item.partition("=")[0]
        if any(t == key or t.startswith(key + ".") for t in targets):
            return key
    return targets[0]


def _restore_urdfs(raw: dict, data: LogData) -> None:
    """Replay with the URDFs the session ran with (attached to the log), not whatever the
    recorded paths hold today: an edited URDF would silently change the replay."""
    for side in ("hsi", "to"):
        robot = raw.get(side)
        robot = robot.get("robot") if isinstance(robot, dict) else None
        if not isinstance(robot, dict):  # --set made it something else: from_dict says what
            continue
        attached = data.attachment(f"urdf/{side}.urdf")
        if robot.get("urdf") and attached is not None:
            target = _replay_dir() / f"{side}.urdf"
            target.write_bytes(attached)
            robot["urdf"] = str(target)


_REPLAY_DIR: tempfile.TemporaryDirectory | None = None


def _replay_dir() -> Path:
    """One temporary folder per process for restored URDFs, removed at exit."""
    global _REPLAY_DIR
    if _REPLAY_DIR is None:
        _REPLAY_DIR = tempfile.TemporaryDirectory(prefix="teleop-rt-replay-")
    return Path(_REPLAY_DIR.name)


def replay_operator(cfg: SessionConfig, data: LogData) -> ScriptedHand | None:
    """The operator load that replays the logged operator input (None: the config's)."""
    kind = data.meta.get("operator", "none")
    hsi = data.topics["/hsi"]
    if kind == "damper":
        return None
    if kind == "hand":
        pos, vel = hsi["operator_reference_m"], hsi["operator_reference_velocity_m_s"]
    else:
        pos, vel = _tool_motion(cfg, hsi["q"])
    if cfg.operator.kind == "hand":
        k, d = cfg.operator.stiffness_n_per_m, cfg.operator.damping_n_s_per_m
    else:
        k, d = PERSON_HAND_STIFFNESS_N_PER_M, PERSON_HAND_DAMPING_N_S_PER_M
    return ScriptedHand(LoggedTrajectory(pos, vel, log_dt(data)), k, d)


def before_first_gap(data: LogData) -> tuple[LogData, str | None]:
    """The ticks a replay can use: the logged operator input is tick-locked, so a log with
    gaps (rows dropped while its writer fell behind) is replayed up to the first; and a note."""
    if not data.gaps:
        return data, None
    first, last = data.gaps[0]
    if first == 0:
        raise LogError(f"{data.path}: ticks 0-{last} are missing; nothing to replay before them")
    note = f"{data.path} has gaps (ticks {first}-{last} first); replayed its first {first} ticks"
    return read_log(data.path, t_to=first * log_dt(data)), note


def take_logged_inputs(site: Site, data: LogData) -> None:
    """Run ``site``'s map as the logged one took the operator's live inputs (the log's
    ``mapping`` metadata: the HSI's ``live_inputs`` bits, the TO's ``follows_packets``), which
    the replay's simulated backend would not give it (a CAN drive's 0x60FD)."""
    logged = logged_mapping(data)
    if site.name == "hsi":
        bits = INPUT_CLUTCH | INPUT_PRESENT
        live, follow = _logged_bits(data, logged, "live_inputs", bits), False
    else:
        live, follow = 0, bool(_logged_bits(data, logged, "follows_packets", 1))
    if live or follow:
        site.mapping.take_live(live, follow)


def logged_mapping(data: LogData) -> dict:
    """The log's ``mapping`` metadata (JSON, ``recorder.mapping_metadata``; {} when it has
    none); a damaged one is a LogError naming it, not a traceback."""
    text = data.meta.get("mapping")
    if text is None:
        return {}
    try:
        value = json.loads(text)
    except ValueError:
        value = None
    if not isinstance(value, dict):
        raise LogError(f"{data.path}: 'teleop_rt' metadata: mapping = {quote(text)} is not a "
                       "JSON object")  # fmt: skip
    return value


def _logged_bits(data: LogData, logged: dict, key: str, most: int) -> int:
    """An integer of the ``mapping`` metadata, 0 to ``most`` (the bits the recorder writes)."""
    value = logged.get(key, 0)
    if type(value) is not int or not 0 <= value <= most:
        raise LogError(f"{data.path}: 'teleop_rt' metadata: mapping's {key} = "
                       f"{quote(json.dumps(value))} is not an integer 0 to {most}")  # fmt: skip
    return value


def logged_inputs(data: LogData) -> np.ndarray | None:
    """The HSI's live inputs per tick (the log's ``inputs``, schema 3), None where it has
    none to replay."""
    robot = data.topics.get("/hsi")
    if robot is None or "inputs" not in (robot.dtype.names or ()):
        return None
    if not logged_mapping(data).get("live_inputs"):
        return None
    return robot["inputs"]


def log_dt(data: LogData) -> float:
    return 1.0 / float(data.meta["rate_hz"])


def _tool_motion(cfg: SessionConfig, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    model = RobotModel.from_spec(cfg.hsi.robot, "hsi")
    pos = np.array([model.ee_position(qk) for qk in q])
    vel = np.gradient(pos, cfg.dt, axis=0) if len(pos) > 1 else np.zeros_like(pos)
    return pos, vel


def build_replay(data: LogData, overrides: list[str]) -> tuple[Session, int]:
    """The replay session and the number of ticks to run (as many as the log holds; a log with
    gaps is replayed up to its first: ``before_first_gap``)."""
    for topic in ("/hsi",):
        if topic not in data.topics:
            raise LogError(f"{data.path}: no {topic} messages to replay")
    require_ticks(data)
    if data.gaps:
        raise LogError(f"{data.path}: ticks {data.gaps[0][0]}-{data.gaps[0][1]} are missing")
    cfg = replay_config(data, overrides)
    session = Session(cfg, operator=replay_operator(cfg, data))
    for site in session.sites:
        take_logged_inputs(site, data)
    inputs = logged_inputs(data)
    if inputs is not None:  # each tick's live inputs, as the logged HSI's map read them
        step, hsi, last = session.step, session.hsi, len(inputs) - 1

        def fed() -> None:
            hsi.feedback.inputs = int(inputs[min(session.tick, last)])
            step()

        session.step = fed  # type: ignore[method-assign]  # (run_loop calls session.step)
    # as long as the log, also when --set rate_hz changed the tick
    return session, round(len(data.topics["/hsi"]) * data.dt / cfg.dt)
