"""Typed, strict session configuration.

``load(path)`` reads a YAML file into a frozen ``SessionConfig``. The schema is strict: an unknown
key, a wrong type or an impossible value raises ``ConfigError`` with one line naming the key.
Per-joint values may be given as one number (used for every joint) or as a list with one entry
per joint; the lengths are checked against the robot models when a session is built.
Relative paths (URDFs, drive EDS files) are resolved against the directory of the config file.
"""

from __future__ import annotations

import ipaddress
import math
from pathlib import Path
from typing import Annotated, Any, Literal, overload

import yaml
from pydantic import (
    BaseModel,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from teleop_rt.com.impairment_spec import ImpairmentSpec
from teleop_rt.declarations import (
    CODEC_RECONSTRUCTION,
    CODEC_RECONSTRUCTIONS,
    DEFAULT_MODE,
    DEFAULT_RECONSTRUCTION,
    EXCHANGE_J,
    EXCHANGE_MIN_TICKS,
    EXCHANGE_WEBER,
    MAX_CODEC_INTERVAL,
    MAX_DELAY_MS,
    MIN_CODEC_INTERVAL,
    PLAYOUT_DEFAULT,
    VELOCITY_GAIN_S_PER_RAD,
    WAVE_DRIFT_TIME_S,
    WAVE_SKIP_TIME_S,
    ChannelMode,
    Playout,
    Reconstruction,
    Space,
    deadband_problem,
)
from teleop_rt.errors import ConfigError, quote
from teleop_rt.hal.can.config import CanSpec
from teleop_rt.inputs import file_problem, read_bounded, shown
from teleop_rt.schema import BOOL_ERROR, StrictModel, annotation_leaves

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PerJointPositive = PositiveFloat | list[PositiveFloat]
PerJointNonNeg = NonNegFloat | list[NonNegFloat]

MAX_CONFIG_BYTES = 1_000_000
MIN_RATE_HZ, MAX_RATE_HZ = 10, 100_000
MAX_TICKS = 100_000_000  # timing statistics are preallocated per tick (16 bytes each)
# Counts of ticks: a detection window longer than the longest session never fires, and every
# count must fit the int64 buffers the tick reads it from (teleop_rt.flat).
TickCount = Annotated[int, Field(ge=0, le=MAX_TICKS)]
MAX_STOP_TICKS = 100_000  # a staged stop that long is no stop (100 s at 1 kHz)
MAX_SEED = 2**63 - 1
CodecTicks = Annotated[int, Field(ge=MIN_CODEC_INTERVAL, le=MAX_CODEC_INTERVAL)]


class Strict(StrictModel):
    """A config section: unknown keys refused, frozen, no boolean taken as a number
    (teleop_rt.schema)."""


def _nonzero_normal(v: list[float]) -> list[float]:
    """A surface's normal: any direction, not the zero vector."""
    if math.hypot(*v) < 1e-9:
        raise ValueError("normal must not be the zero vector")
    return v


def _vec3(values: list[float], key: str) -> list[float]:
    if len(values) not in (2, 3):
        raise ValueError(f"{key} needs 2 (x, y) or 3 (x, y, z) numbers, got {len(values)}")
    return list(values)


class RobotSpec(Strict):
    """Where a robot's kinematics and dynamics come from: a URDF file or example-robot-data."""

    urdf: Path | None = None
    example_robot: str | None = None
    ee_frame: str | None = None  # default: the last frame of the model
    q0_rad: list[FiniteFloat] | None = None  # default: zeros
    # joints taken out of the model (pinocchio.buildReducedModel), held rigid at the model's
    # neutral position, e.g. a gripper's fingers: the per-joint parameters and q0_rad are then
    # the other joints', and neither the tool Jacobian nor the guard sees them
    locked_joints: list[str] = Field(default_factory=list)

    @model_validator(mode="after")
    def _one_source(self) -> RobotSpec:
        if (self.urdf is None) == (self.example_robot is None):
            raise ValueError("give exactly one of 'urdf' or 'example_robot'")
        return self

    @field_validator("locked_joints")
    @classmethod
    def _locked_once(cls, v: list[str]) -> list[str]:
        twice = sorted({name for name in v if v.count(name) > 1})
        if twice:
            raise ValueError(f"names a joint more than once: {', '.join(twice)}")
        return v


class ControllerSpec(Strict):
    """A P or PID law per joint: out = kp e + ki integral(e) + kd de/dt (filtered)."""

    kind: Literal["p", "pid"] = "p"
    kp: PerJointNonNeg
    ki: PerJointNonNeg = 0.0
    kd: PerJointNonNeg = 0.0
    derivative_filter_s: NonNegFloat = 0.0
    # Anti-windup: the integral term's contribution is clamped to +-integral_limit and the
    # integrator stops while the output is saturated at +-output_limit (None: no limit).
    integral_limit: PerJointPositive | None = None
    output_limit: PerJointPositive | None = None

    @model_validator(mode="after")
    def _p_has_no_i_d(self) -> ControllerSpec:
        if self.kind == "p" and (_any_nonzero(self.ki) or _any_nonzero(self.kd)):
            raise ValueError("kind 'p' takes only kp; set kind: pid to use ki or kd")
        return self

    @field_validator("kp")
    @classmethod
    def _p_needs_kp(cls, kp: float | list[float], info: Any) -> float | list[float]:
        if info.data.get("kind") == "p" and not all(kp if isinstance(kp, list) else [kp]):
            raise ValueError("must be > 0 with kind 'p' (a zero gain controls nothing)")
        return kp


def _any_nonzero(x: float | list[float]) -> bool:
    return any(v != 0 for v in (x if isinstance(x, list) else [x]))


class SideSpec(Strict):
    """One robot of the pair: its model, virtual mass (eq 3 / 13) and controller (eq 4 / 14)."""

    robot: RobotSpec
    virtual_mass: PerJointPositive  # kg m^2 per joint (M1 or M2 of the paper)
    controller: ControllerSpec
    compensate_friction: bool = True  # include the model's joint friction in n(q, v)
    backend: str | None = None  # this robot's backend; default: the session's ``backend``


class DeadbandSpec(Strict):
    """The perceptual deadband codec's parameters (``channel.codec: deadband``): a site sends
    when its signal (a wave channel's outgoing wave; TDPA's velocity at the HSI, torque at the
    TO) leaves ``weber * |last sent| + floor`` on any joint, no sooner than ``min_interval_ticks``
    and no later than ``max_interval_ticks`` after its last packet."""

    weber_hsi: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.10
    weber_to: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.10
    # absolute floor, in the signal's units (a wave's sqrt(W); rad/s at a TDPA HSI, N m at its
    # TO): near zero a relative band alone would send at every sign change
    floor_hsi: NonNegFloat = 0.01
    floor_to: NonNegFloat = 0.01
    min_interval_ticks: CodecTicks = 1
    max_interval_ticks: CodecTicks = 100
    # velocity-adaptive deadband (Kammerl et al., Presence 2010): the Weber fraction grows
    # with the port's velocity, weber * (1 + gain |omega|); 0 keeps it constant
    velocity_gain_s_per_rad: NonNegFloat = VELOCITY_GAIN_S_PER_RAD
    # how the peer reconstructs a site's signal between its packets: linear extrapolates the
    # last two (Hinterseer et al., IEEE Trans. Signal Process. 56(2), 2008), hold keeps the
    # last one; None: the channel mode's measured best (teleop_rt.com.codec.PREDICTIONS_BY_MODE)
    prediction_hsi: Literal["linear", "hold"] | None = None
    prediction_to: Literal["linear", "hold"] | None = None
    # TDPA only: a site also sends once this much energy has crossed its port, in or out, since
    # its last packet (the energy deadband of teleop_rt.com.codec; docs/codec.md measures it at
    # D = 1 ms, where the hold's lag costs felt stiffness); 0: off
    exchange_j: NonNegFloat = EXCHANGE_J
    # ... and that step grows by this fraction of the energy crossed over the last
    # codec.EXCHANGE_WINDOW_TICKS (Weber's rule on the energy: a steady flow, foam's damping,
    # sends a packet per fraction of the window); 0: the fixed step
    exchange_weber: NonNegFloat = EXCHANGE_WEBER
    # ... and it sends no sooner than this many ticks after the last packet (the deadband's
    # own crossings still go out at once; docs/codec.md, "the energy deadband's pace"); 1: off
    exchange_min_ticks: CodecTicks = EXCHANGE_MIN_TICKS

    @model_validator(mode="after")
    def _intervals(self) -> DeadbandSpec:
        # (the fields' own bounds are their types; the rules between them are the codec's)
        for side in ("hsi", "to"):
            problem = deadband_problem(
                getattr(self, f"weber_{side}"), getattr(self, f"floor_{side}"),
                self.min_interval_ticks, self.max_interval_ticks, self.velocity_gain_s_per_rad,
                self.exchange_j, self.exchange_weber, self.exchange_min_ticks,
            )
            if problem:
                raise ValueError(problem)
        return self


class ChannelSpec(Strict):
    """The COM (teleop_rt.com.port): a wave-variable (scattering) channel, the time-domain
    passivity approach (tdpa: delayed velocity forward, torque back, with passivity observers
    and controllers), or, for comparison, plain delayed force feedback (direct, not passive)."""

    mode: ChannelMode = DEFAULT_MODE
    delay_ms: Annotated[float, Field(ge=0, le=MAX_DELAY_MS, allow_inf_nan=False)] = 0.0
    wave_impedance: PerJointPositive = 2.0  # b, N m s/rad per joint
    # First-order low-pass on each received wave (keeps the channel passive; damps the
    # ringing of the discrete terminations against stiff contact). None switches it off.
    wave_filter_hz: PositiveFloat | None = 30.0
    # What a wave channel does with a packet that did not arrive: bounded (the wave integral
    # within an honest energy bound: passive, and it catches up lost samples), corrected
    # (bounded, and the integral an outage lost paid back within the same budget: no position
    # drift), reflected (corrected, and a port may emit beyond its budget what it reflects,
    # taken off the energy it declares to the peer: a push is held through a loss), zero (a
    # zero wave: passive), and, unprotected, for comparison: hold (the last wave held) or
    # integral (the wave integral without the bound). With no loss all six compute the same.
    # With the deadband codec: reflected (the default) or bounded, the two it keeps passive.
    wave_reconstruction: Reconstruction = DEFAULT_RECONSTRUCTION
    # corrected's and reflected's drift correction: the wave integral's debt is paid back with
    # this time constant, s (longer: less of the pay-back felt after a delay step down, more
    # position lost meanwhile; docs/transparency_under_loss.md, "s36")
    wave_drift_time_s: PositiveFloat = WAVE_DRIFT_TIME_S
    # the part of that debt a change of the delay brought under the newest playout (packets
    # skipped, or ticks inserted) paid back with this time constant, s, an outage's and a
    # loss's with wave_drift_time_s; None (the default): one debt (docs/transparency_under_loss.md,
    # "s37": 2 s meets the foam sawtooth row, costs T_p under jitter)
    wave_skip_time_s: PositiveFloat | None = WAVE_SKIP_TIME_S
    # the wave impedance scheduled by the delay each port measures (a packet's age): b D / age,
    # between WAVE_B_FLOOR b and b, rate-limited (teleop_rt.com.port.schedule_b); off, the
    # default: b as configured (docs/transparency_under_loss.md, "s38")
    wave_impedance_schedule: bool = False
    # TDPA's position-drift compensation: the TO moves toward the HSI's position with this
    # time constant, within what its passivity controller allows (better T_p, worse T_tau:
    # docs/passivity.md). None, the default, switches it off.
    tdpa_drift_time_s: PositiveFloat | None = None
    # Haptic data reduction (teleop_rt.com.codec): none sends a packet every tick; deadband
    # sends one only when the signal leaves its perceptual deadband (or the maximum interval
    # is up), the receiver holding the last one passively in between (docs/codec.md)
    codec: Literal["none", "deadband"] = "none"
    deadband: DeadbandSpec = DeadbandSpec()

    @model_validator(mode="before")
    @classmethod
    def _codec_default_reconstruction(cls, data: Any) -> Any:
        """The deadband codec's wave reconstruction, unless given: CODEC_RECONSTRUCTION (one it
        keeps passive; teleop_rt.com.codec)."""
        if isinstance(data, dict) and data.get("codec", "none") != "none":
            data = {"wave_reconstruction": CODEC_RECONSTRUCTION, **data}
        return data
    # what the channel couples (teleop_rt.mapping): joint j to joint j, or the tools in task
    # space, each site through its own Jacobian: the plane (x, y), position (x, y, z) or the
    # pose (x, y, z and the orientation; wave_impedance then in N s/m, for the pose per
    # component: 3 in N s/m, then 3 in N m s/rad)
    space: Space = "joint"


class FaultSpec(Strict):
    """A fault injected into the simulated plant during [start_s, start_s + duration_s).

    nan: the measured torque reads NaN; dropout: the sensors stop updating (stale feedback);
    noise_burst: Gaussian noise of std ``magnitude`` N m on the measured torque; bias: the
    measured torque is off by ``magnitude`` N m; saturation: the motor delivers at most
    ``magnitude`` N m; stuck: the joint is held where it is.
    """

    kind: Literal["nan", "dropout", "noise_burst", "bias", "saturation", "stuck"]
    robot: Literal["hsi", "to"]
    joint: Annotated[int, Field(ge=0)] = 0
    start_s: NonNegFloat = 0.0
    duration_s: PositiveFloat = 1e9
    magnitude: NonNegFloat = 1.0


class PlantSpec(Strict):
    """The simulated plant: integrator, sub-steps, sensor models and injected faults."""

    integrator: Literal["semi_implicit_euler", "rk4"] = "semi_implicit_euler"
    substeps: Annotated[int, Field(ge=1, le=100)] = 1
    torque_noise_std_nm: NonNegFloat = 0.0
    velocity_noise_std_rad_s: NonNegFloat = 0.0
    # Coulomb friction is smoothed as f_c * tanh(v / v_s) so the stiff sign() never enters.
    coulomb_smoothing_rad_s: Annotated[float, Field(ge=1e-6, le=10.0)] = 0.01
    faults: list[FaultSpec] = Field(default_factory=list)


class WorkspaceBox(Strict):
    """An axis-aligned box (world frame, m) the robot's tool frame (``ee_frame``) must stay in;
    2 numbers bound x and y only, 3 also z."""

    lower_m: list[FiniteFloat]
    upper_m: list[FiniteFloat]

    @model_validator(mode="after")
    def _box(self) -> WorkspaceBox:
        _vec3(self.lower_m, "lower_m")
        _vec3(self.upper_m, "upper_m")
        if len(self.lower_m) != len(self.upper_m):
            raise ValueError("lower_m and upper_m need the same number of axes")
        if any(lo >= hi for lo, hi in zip(self.lower_m, self.upper_m, strict=True)):
            raise ValueError("every lower_m must be below its upper_m")
        return self


class WorkspaceLimits(Strict):
    """End-effector workspace boxes per robot (none by default: the joint limits bound it)."""

    hsi: WorkspaceBox | None = None
    to: WorkspaceBox | None = None


class VirtualWall(Strict):
    """A virtual wall in the TO's plane: the line through point_m (x, y) with unit normal
    pointing to the allowed side; beyond it a unilateral spring-damper pushes the TO's tool
    back, rendered as part of its environment (teleop_rt.task_limits)."""

    point_m: list[FiniteFloat]
    normal: list[FiniteFloat]
    stiffness_n_per_m: PositiveFloat
    damping_n_s_per_m: NonNegFloat = 0.0

    @field_validator("point_m", "normal")
    @classmethod
    def _xy(cls, v: list[float], info: Any) -> list[float]:
        if len(v) != 2:
            raise ValueError(f"{info.field_name} needs 2 numbers (x, y: the plane), got {len(v)}")
        return list(v)

    _nonzero = field_validator("normal")(classmethod(lambda cls, v: _nonzero_normal(v)))


class ToolLimits(Strict):
    """The TO's limits in task space (channel.space: plane; teleop_rt.task_limits): all off by
    default, so joint-space runs compute what they did."""

    # the tool's speed in the plane: above it the TO's coupling gain is capped (a lossless
    # transformer: motion and fed-back force scaled alike) until it is below again
    speed_limit_m_s: PositiveFloat | None = None
    # the TO's measured force at the tool (J#^T tau_e) above this: a safety stop
    force_limit_n: PositiveFloat | None = None
    walls: list[VirtualWall] = Field(default_factory=list)

    @property
    def active(self) -> bool:
        return (self.speed_limit_m_s is not None or self.force_limit_n is not None
                or bool(self.walls))  # fmt: skip


class SafetySpec(Strict):
    """The safety layer (teleop_rt/safety.py): limits come from the URDFs."""

    enabled: bool = True
    position_limits: bool = True  # stop outside the URDF joint limits
    velocity_limits: bool = True  # stop above the URDF velocity limits
    torque_limits: Literal["saturate", "stop", "off"] = "saturate"  # URDF effort limits
    # a torque pinned at its limit this many ticks in a row is a fault (a loop gone unstable,
    # a stuck joint), not a transient: stop. 0 never stops for saturation.
    saturation_stop_ticks: Annotated[int, Field(ge=0, le=MAX_TICKS)] = 200
    # feedback that has not been refreshed for this many ticks is stale: stop
    stale_ticks: Annotated[int, Field(ge=1, le=MAX_TICKS)] = 3
    # a joint whose measured acceleration misses the commanded virtual dynamics (eq 3 / 13) by
    # more than this, this many ticks in a row, does not follow its torque (saturated or
    # blocked actuator, broken model): stop. 0 ticks switches the check off.
    tracking_error_rad_s2: PositiveFloat = 20.0
    tracking_error_ticks: Annotated[int, Field(ge=0, le=MAX_TICKS)] = 20
    # the tool frame outside its box is a stop (one forward-kinematics call per boxed robot)
    workspace: WorkspaceLimits = WorkspaceLimits()
    # the TO's tool speed, force and virtual walls in task space (none by default)
    tool: ToolLimits = ToolLimits()
    # plausibility of the measurements (sensor faults), checked whatever ``enabled`` says:
    # |tau_ext| above this (N m per joint; default 3 x the URDF effort limit) and |v| above
    # this (rad/s per joint; default 2 x the URDF velocity limit) stop within the tick
    measured_torque_limit_nm: PerJointPositive | None = None
    measured_velocity_limit_rad_s: PerJointPositive | None = None
    # the stop itself: the HSI is damped, the TO is brought to rest, then both get zero torque
    stop_damping_nm_s_per_rad: NonNegFloat = 0.5
    stop_max_ticks: Annotated[int, Field(ge=0, le=MAX_STOP_TICKS)] = 500


class RecordingSpec(Strict):
    """The log (teleop_rt/recording/recorder.py): the tick never waits for its writer."""

    # rows the writer cannot take (its ring full, the writer dead, the disk full): "stop" ends
    # the session at the tick boundary as Ctrl-C does; "continue" keeps the robots running and
    # counts the ticks missing from the log. Either way the log is reported incomplete (exit 4).
    on_loss: Literal["stop", "continue"] = "stop"
    # how far the writer may fall behind the loop before rows are lost (the ring's size)
    ring_s: Annotated[float, Field(gt=0, le=600, allow_inf_nan=False)] = 64.0
    # the 3D scene's messages (/tf, /environment, /hand_target) per second of session time: its
    # transforms are the writer's largest cost after the four 1 kHz topics (about 1 us a tick
    # at 50 Hz); at most one per tick; 0: no 3D topics
    scene_hz: Annotated[float, Field(ge=0, le=1000, allow_inf_nan=False)] = 50.0


class Interval(Strict):
    """A stretch of time [start_s, end_s)."""

    start_s: NonNegFloat
    end_s: PositiveFloat

    @model_validator(mode="after")
    def _ordered(self) -> Interval:
        if not self.end_s > self.start_s:
            raise ValueError("end_s must be after start_s")
        return self


def _disjoint(intervals: list[Interval]) -> list[Interval]:
    if any(b.start_s < a.end_s for a, b in zip(intervals, intervals[1:], strict=False)):
        raise ValueError("intervals must be in time order and must not overlap")
    return intervals


class OperatorInputs(Strict):
    """The operator's digital inputs, scripted (teleop_rt.mapping): the clutch pressed (the
    sites decoupled, for indexing) and the presence switch released (the operator away: as
    the clutch, and a stop after mapping.presence_timeout_s)."""

    clutch: list[Interval] = Field(default_factory=list)
    absent: list[Interval] = Field(default_factory=list)

    @field_validator("clutch", "absent")
    @classmethod
    def _in_order(cls, v: list[Interval]) -> list[Interval]:
        return _disjoint(v)


class DamperOperatorSpec(OperatorInputs):
    """The paper's operator (Z_o = const): a damper between the HSI joints and the ground."""

    kind: Literal["damper"]
    damping_nm_s_per_rad: PerJointNonNeg = 10.0


class Waypoint(Strict):
    t_s: NonNegFloat
    position_m: list[FiniteFloat]

    @field_validator("position_m")
    @classmethod
    def _xyz(cls, v: list[float]) -> list[float]:
        return _vec3(v, "position_m")


class HandOperatorSpec(OperatorInputs):
    """An active operator: a hand following scripted end-effector waypoints (minimum-jerk
    segments from the HSI's start pose) through a Cartesian spring-damper."""

    kind: Literal["hand"]
    stiffness_n_per_m: PositiveFloat = 300.0
    damping_n_s_per_m: NonNegFloat = 20.0
    waypoints: list[Waypoint] = Field(min_length=1)

    @field_validator("waypoints")
    @classmethod
    def _increasing(cls, wps: list[Waypoint]) -> list[Waypoint]:
        times = [w.t_s for w in wps]
        if any(b <= a for a, b in zip(times, times[1:], strict=False)) or times[0] <= 0:
            raise ValueError("waypoint times must be > 0 and strictly increasing")
        return wps


Operator = Annotated[DamperOperatorSpec | HandOperatorSpec, Field(discriminator="kind")]


class HalfPlane(Strict):
    """A contact surface: the plane through point_m with unit normal pointing to free space."""

    point_m: list[FiniteFloat]
    normal: list[FiniteFloat]

    @field_validator("point_m", "normal")
    @classmethod
    def _xyz(cls, v: list[float], info: Any) -> list[float]:
        return _vec3(v, info.field_name)

    _nonzero = field_validator("normal")(classmethod(lambda cls, v: _nonzero_normal(v)))


class WallSpec(HalfPlane):
    """Unilateral spring-damper: a stiff wall (kind wall) or soft foam (kind foam)."""

    kind: Literal["wall", "foam"]
    stiffness_n_per_m: PositiveFloat
    damping_n_s_per_m: NonNegFloat = 0.0


class SpringSpec(HalfPlane):
    """Bilateral spring and/or damper along the normal, rest position at point_m."""

    kind: Literal["spring", "damper"]
    stiffness_n_per_m: NonNegFloat = 0.0
    damping_n_s_per_m: NonNegFloat = 0.0


class MassSpec(HalfPlane):
    """A free mass resting against the plane (moves along the normal once pushed), coupled to
    the end-effector by a stiff unilateral contact (or held: attached: true)."""

    kind: Literal["mass"]
    mass_kg: PositiveFloat
    attached: bool = False
    contact_stiffness_n_per_m: PositiveFloat = 20000.0
    contact_damping_n_s_per_m: NonNegFloat = 50.0


Environment = Annotated[WallSpec | SpringSpec | MassSpec, Field(discriminator="kind")]


class ZenohEndpoints(Strict):
    """Where one site's Zenoh session listens and what it connects to (Zenoh locators such as
    ``udp/127.0.0.1:7447``, ``tcp/host:7447``, ``tls/host:7447``)."""

    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list)
    # tests only: this site's tick clock runs this many ppm fast (> 0) or slow, as a host's
    # crystal does, to show the receivers following it (teleop_rt.com.drift)
    clock_ppm: Annotated[float, Field(ge=-10_000, le=10_000, allow_inf_nan=False)] = 0.0

    @field_validator("listen", "connect")
    @classmethod
    def _locators(cls, v: list[str]) -> list[str]:
        for locator in v:
            _check_locator(locator)
        return v


# Zenoh's locators over IP (PROTO/HOST:PORT); others (unixsock-stream/PATH, serial/...) are
# left to Zenoh to judge
IP_SCHEMES = ("udp", "tcp", "tls", "quic", "ws")


def _check_locator(locator: str) -> None:
    """A locator ``check`` can judge as the site would: else Zenoh refuses it only when the
    site opens its session ('invalid port value'), after a check that said ok."""
    scheme, sep, rest = locator.partition("/")
    if not sep or not scheme or not rest:
        raise ValueError(f"{locator!r} is not a Zenoh locator (PROTO/ADDRESS, e.g. "
                         "udp/127.0.0.1:7447)")  # fmt: skip
    if scheme.lower() not in IP_SCHEMES:
        return
    address = rest.split("?", 1)[0].split("#", 1)[0]
    host, colon, port = address.rpartition(":")
    if not colon or not host or host == "[]":
        raise ValueError(
            f"{locator!r} needs HOST:PORT after {scheme}/ (e.g. {scheme}/127.0.0.1:7447)"
        )
    if not (port.isdigit() and int(port) <= 65535):
        raise ValueError(f"{locator!r}: the port must be a whole number 0..65535, not {port!r}")


class TlsFiles(Strict):
    certificate: Path  # PEM, with a subjectAltName matching the endpoint's host name
    private_key: Path


class TlsSpec(Strict):
    """Mutual TLS: both sites' certificates signed by ``root_ca``; a peer without one is never
    connected (paths relative to the config file, like URDFs)."""

    root_ca: Path
    hsi: TlsFiles
    to: TlsFiles


class ZenohSpec(Strict):
    """The Zenoh link (teleop_rt.com.zenoh_link): peer mode by default (client: through a
    router, for sites behind NAT), multicast scouting always off, explicit endpoints.

    Without TLS nobody on the link is authenticated: whoever reaches an endpoint can drive the
    robots. So an endpoint beyond loopback (127.0.0.0/8, ::1, localhost) needs ``tls`` and a
    tls/ or quic/ locator, unless ``allow_insecure`` says otherwise (a warning then)."""

    mode: Literal["peer", "client"] = "peer"
    hsi: ZenohEndpoints = ZenohEndpoints(listen=["udp/127.0.0.1:7447"])
    to: ZenohEndpoints = ZenohEndpoints(connect=["udp/127.0.0.1:7447"])
    tls: TlsSpec | None = None
    allow_insecure: bool = False

    @model_validator(mode="after")
    def _tls_beyond_loopback(self) -> ZenohSpec:
        exposed = insecure_endpoints(self)
        if exposed and not self.allow_insecure:
            raise ValueError(
                f"{exposed[0].removeprefix('link.zenoh.')} is not a loopback endpoint and the "
                "link has no TLS: anyone who "
                "reaches it could drive the robots (use tls/ endpoints with link.zenoh.tls, or "
                "set link.zenoh.allow_insecure: true)"
            )
        return self


SECURE_SCHEMES = ("tls", "quic")  # Zenoh's locators that run TLS (with link.zenoh.tls)


def locator_host(locator: str) -> tuple[str, str]:
    """A Zenoh locator's scheme and host: ``udp/[::1]:7447?x#y`` -> ('udp', '::1')."""
    scheme, _, rest = locator.partition("/")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if address.startswith("["):
        host = address[1 : address.find("]")] if "]" in address else address[1:]
    else:
        host = address.rsplit(":", 1)[0] if ":" in address else address
    return scheme.lower(), host


def is_loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.split("%", 1)[0]).is_loopback
    except ValueError:  # a host name: it may resolve anywhere
        return False


def insecure_endpoints(spec: ZenohSpec) -> list[str]:
    """Each site's endpoints (as ``link.zenoh.<site>.<listen|connect>: LOCATOR``) that reach
    beyond loopback without TLS (not a tls/ or quic/ locator, or no ``tls`` section)."""
    out = []
    for site in ("hsi", "to"):
        ends: ZenohEndpoints = getattr(spec, site)
        for kind in ("listen", "connect"):
            for locator in getattr(ends, kind):
                scheme, host = locator_host(locator)
                if scheme == "unixsock-stream" or is_loopback(host):
                    continue  # this host only
                if spec.tls is None or scheme not in SECURE_SCHEMES:
                    out.append(f"link.zenoh.{site}.{kind}: {locator}")
    return out


class LinkSpec(Strict):
    """What carries the packets between the two sites (teleop_rt.com)."""

    kind: Literal["inprocess", "zenoh"] = "inprocess"
    # the key expressions: KEY/<session name>/<site>/...
    key: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")] = "teleop_rt"
    # no packet from the peer for this long: the site stops its robot (staged stop)
    peer_timeout_ms: Annotated[float, Field(gt=0, le=10_000, allow_inf_nan=False)] = 50.0
    # the peer must appear (and agree on the session) within this, else the site refuses
    handshake_timeout_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)] = 10.0
    # the receiver follows a peer whose clock drifts by at most one tick per 1e6 / this many
    # ticks (teleop_rt.com.drift; 0: never)
    max_drift_ppm: Annotated[float, Field(ge=0, le=10_000, allow_inf_nan=False)] = 200.0
    zenoh: ZenohSpec = ZenohSpec()
    # a seeded network emulation between the sites: delay, jitter, loss, bursts, duplication,
    # reordering, traces; in one process (fast mode, bit-reproducible) and in front of Zenoh
    # (each site holds its own packets until their instant: teleop_rt.com.zenoh_link)
    impairment: ImpairmentSpec | None = None
    # which packet a site uses at its tick k (teleop_rt.declarations.Playout)
    playout: Playout = PLAYOUT_DEFAULT


class MappingSpec(Strict):
    """The map between each robot and its port of the channel (teleop_rt.mapping): motion and
    force scaling, kept passive, and how the coupling comes back after the clutch or an
    absence. Joint space: joint j of the HSI maps to joint j of the TO."""

    motion_scale: PositiveFloat = 1.0  # alpha: the TO moves alpha times the HSI's motion
    force_scale: PositiveFloat = 1.0  # beta: the HSI displays beta times the TO's torque
    # on re-engaging the coupling gain ramps 0 -> 1 over at least this long, and changes the
    # torque it multiplies by at most engage_step_nm per tick
    engage_ramp_s: NonNegFloat = 0.2
    engage_step_nm: PositiveFloat = 0.005
    # the operator away (operator.absent) for longer than this: a safety stop (None: never)
    presence_timeout_s: PositiveFloat | None = None
    # channel.space: pose, at the TO: the gain K (1/s) of its orientation's correction toward
    # the orientation the channel commanded, integrated on SO(3) (0: none)
    orientation_gain_per_s: NonNegFloat = 5.0
    # task space, a redundant TO (more joints than the task's directions): the gain k_p (1/s)
    # of its posture task, v_ref += (I - J# J) k_p (posture_rad - q), which moves the joints
    # in the tool Jacobian's null space only (0: none), and the posture (default: the TO's
    # configuration at its first tick; one angle per joint, within the joint limits)
    posture_gain_per_s: NonNegFloat = 0.0
    posture_rad: list[FiniteFloat] | None = None
    # the TO's frame against the HSI's (task space only; teleop_rt.mapping): the TO's tool is
    # to be at R (alpha x_hsi) + offset_m, R from roll, pitch, yaw about the fixed x, y, z
    # axes (URDF's rpy), in the pose its orientation at R R_hsi; in the plane only a yaw and
    # an x, y offset
    offset_m: tuple[FiniteFloat, FiniteFloat, FiniteFloat] = (0.0, 0.0, 0.0)
    rotation_rpy_deg: tuple[FiniteFloat, FiniteFloat, FiniteFloat] = (0.0, 0.0, 0.0)
    # the HSI's clutch and presence from the terminal's keys (teleop-rt run --keys, site
    # --keys: teleop_rt.keys); the TO then follows the HSI's packets' coupling state
    keys: bool = False

    @property
    def framed(self) -> bool:
        """An offset or a rotation between the frames is given."""
        return any(self.offset_m) or any(self.rotation_rpy_deg)


class SessionConfig(Strict):
    """A whole session: rate, duration, both robots, the channel, plant, operator, environment."""

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")] = "session"
    rate_hz: Annotated[int, Field(ge=MIN_RATE_HZ, le=MAX_RATE_HZ)] = 1000
    duration_s: PositiveFloat = 10.0
    seed: Annotated[int, Field(ge=0, le=MAX_SEED)] = 0
    backend: str = "sim"  # a name from the backend registry (teleop_rt.hal)
    hsi: SideSpec
    to: SideSpec
    channel: ChannelSpec = ChannelSpec()
    plant: PlantSpec = PlantSpec()
    safety: SafetySpec = SafetySpec()
    recording: RecordingSpec = RecordingSpec()
    link: LinkSpec = LinkSpec()
    operator: Operator
    environment: list[Environment] = Field(default_factory=list)
    can: CanSpec | None = None  # the CAN backend's buses and drives (teleop_rt.hal.can)
    mapping: MappingSpec = MappingSpec()  # scaling, clutch and presence (teleop_rt.mapping)

    @field_validator("duration_s")
    @classmethod
    def _duration_ticks(cls, v: float, info: Any) -> float:
        rate = info.data.get("rate_hz")
        if rate is not None and not (v * rate <= MAX_TICKS and ticks_in(v, rate) >= 1):
            raise ValueError(
                f"{v:g} s is {v * rate:.3g} ticks at rate_hz = {rate}; "
                f"a session runs 1 to {MAX_TICKS} ticks"
            )
        return v

    @model_validator(mode="after")
    def _tool_frames_named(self) -> SessionConfig:
        # a robot's last frame is not necessarily its tool (example-robot-data's double
        # pendulum ends at the elbow): Cartesian loads need the point named explicitly
        if self.operator.kind == "hand" and self.hsi.robot.ee_frame is None:
            raise ValueError("hsi.robot.ee_frame: required with a hand operator (the held point)")
        if self.environment and self.to.robot.ee_frame is None:
            raise ValueError("to.robot.ee_frame: required with an environment (the contact point)")
        return self

    @model_validator(mode="after")
    def _delay_whole_ticks(self) -> SessionConfig:
        ticks = self._delay_in_ticks()
        if abs(ticks - round(ticks)) > 1e-9:
            raise ValueError(
                f"channel.delay_ms = {self.channel.delay_ms} is not a whole number of "
                f"{1000.0 / self.rate_hz:g} ms ticks at rate_hz = {self.rate_hz}"
            )
        return self

    @model_validator(mode="after")
    def _codec_fits(self) -> SessionConfig:
        ch = self.channel
        if ch.codec == "none":
            return self
        if ch.mode == "direct":
            raise ValueError(
                "channel.codec: the deadband codec needs a passive channel (mode wave or "
                "tdpa); direct force feedback has no reconstruction to keep passive"
            )
        if self.delay_ticks < 1:
            raise ValueError(
                "channel.codec: the deadband codec needs channel.delay_ms of at least one tick "
                "(with no delay the ports couple directly, every tick)"
            )
        if ch.mode == "wave" and ch.wave_reconstruction not in CODEC_RECONSTRUCTIONS:
            raise ValueError(
                "channel.codec: the deadband codec holds a wave channel's waves within an "
                "energy bound; channel.wave_reconstruction must be "
                f"{' or '.join(CODEC_RECONSTRUCTIONS)}, not {ch.wave_reconstruction}"
            )
        if ch.mode == "wave" and ch.deadband.exchange_j > 0:
            raise ValueError(
                "channel.deadband.exchange_j: the energy deadband is TDPA's (a wave channel's "
                "codec bounds the waves' energy itself); set it to 0 or channel.mode: tdpa"
            )
        return self

    @model_validator(mode="after")
    def _keys_on_a_backend_without_inputs(self) -> SessionConfig:
        if self.mapping.keys and self.backend_for("hsi") == "can":
            raise ValueError(
                "mapping.keys: the CAN backend sets the HSI's operator inputs from its drives' "
                "0x60FD (can.hsi.clutch_input, presence_input); the keys need another backend"
            )
        return self

    @model_validator(mode="after")
    def _tool_limits_in_task_space(self) -> SessionConfig:
        if self.safety.tool.active and self.channel.space != "plane":
            raise ValueError(
                "safety.tool: the tool's limits act in the task's plane; they need "
                f"channel.space: plane (not {self.channel.space})"
            )
        return self

    @model_validator(mode="after")
    def _frames_in_task_space(self) -> SessionConfig:
        m = self.mapping
        if m.framed and self.channel.space == "joint":
            raise ValueError(
                "mapping.offset_m, mapping.rotation_rpy_deg: frames are mapped in task space; "
                "they need channel.space: plane, position or pose"
            )
        if self.channel.space == "plane" and (m.offset_m[2] or any(m.rotation_rpy_deg[:2])):
            raise ValueError(
                "mapping: in the plane (channel.space: plane) the frames differ by an x, y "
                "offset and a yaw only: offset_m's z and rotation_rpy_deg's roll and pitch "
                "must be 0"
            )
        return self

    @model_validator(mode="after")
    def _posture_in_task_space(self) -> SessionConfig:
        m = self.mapping
        if m.posture_rad is not None and self.channel.space == "joint":
            raise ValueError(
                "mapping.posture_rad: the posture task acts in the null space of the TO's tool "
                "Jacobian; it needs channel.space: plane, position or pose"
            )
        if m.posture_gain_per_s > 0 and self.channel.space == "joint":
            raise ValueError(
                "mapping.posture_gain_per_s: the posture task acts in the null space of the "
                "TO's tool Jacobian; it needs channel.space: plane, position or pose (0 turns "
                "it off)"
            )
        if m.posture_rad is not None and m.posture_gain_per_s == 0:
            raise ValueError(
                "mapping.posture_rad: the posture acts with mapping.posture_gain_per_s > 0 "
                "(its gain k_p, 1/s; 0 turns the posture task off)"
            )
        return self

    @model_validator(mode="after")
    def _impedance_schedule_needs_its_correction(self) -> SessionConfig:
        # the schedule's b, moving, drifts the TO off the HSI; its correction rides on the
        # drift correction of corrected/reflected, and the deadband codec's held ticks would
        # read as aged packets (teleop_rt.com.port.schedule_b)
        c = self.channel
        if c.wave_impedance_schedule and (
            c.mode != "wave" or c.wave_reconstruction not in ("corrected", "reflected")
            or c.codec != "none"
        ):
            raise ValueError(
                "channel.wave_impedance_schedule needs channel.mode wave with "
                "wave_reconstruction corrected or reflected and codec none"
            )
        return self

    @model_validator(mode="after")
    def _time_constants_of_a_tick_or_more(self) -> SessionConfig:
        # paid back per tick as debt (1 - dt / T): below a tick it overshoots, below half a
        # tick it grows without bound (inf, NaN in the ports: teleop_rt.com.port)
        c = self.channel
        for key in ("wave_drift_time_s", "wave_skip_time_s", "tdpa_drift_time_s"):
            t = getattr(c, key)
            if t is not None and t < self.dt:
                raise ValueError(
                    f"channel.{key} = {t:g} s is shorter than one tick ({self.dt:g} s at "
                    f"rate_hz = {self.rate_hz}): a debt paid back faster than a tick overshoots"
                )
        return self

    @model_validator(mode="after")
    def _filter_below_nyquist(self) -> SessionConfig:
        cutoff, nyquist = self.channel.wave_filter_hz, self.rate_hz / 2.0
        if cutoff is not None and cutoff >= nyquist:
            raise ValueError(
                f"channel.wave_filter_hz = {cutoff:g} Hz is not below the Nyquist frequency "
                f"({nyquist:g} Hz at rate_hz = {self.rate_hz}); null turns the filter off"
            )
        return self

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    def backend_for(self, side: str) -> str:
        """The backend of robot ``side`` ('hsi' or 'to'): its own, else the session's."""
        return getattr(self, side).backend or self.backend

    @property
    def backends(self) -> dict[str, str]:
        return {side: self.backend_for(side) for side in ("hsi", "to")}

    def _delay_in_ticks(self) -> float:
        return self.channel.delay_ms * self.rate_hz / 1000.0

    @property
    def delay_ticks(self) -> int:
        return round(self._delay_in_ticks())

    @property
    def n_ticks(self) -> int:
        return ticks_in(self.duration_s, self.rate_hz)


def ticks_in(seconds: float, rate_hz: float) -> int:
    """The whole ticks in ``seconds`` at ``rate_hz``, rounded half up (not half even)."""
    return math.floor(seconds * rate_hz + 0.5)


def _format_error(err: ValidationError) -> str:
    errors = err.errors()
    first = _pick_error(errors)
    loc_parts = first["loc"]
    keep_last = first["type"] == "extra_forbidden"  # the user's own (unknown) key
    loc = ".".join(
        str(p)
        for i, p in enumerate(loc_parts)
        if not _is_union_tag(p, loc_parts[i - 1] if i else None)
        and not (_is_member_tag(p) and not (keep_last and i == len(loc_parts) - 1))
    )
    msg = first["msg"].removeprefix("Value error, ")
    if first["type"] == BOOL_ERROR:  # raised for the whole section: the key is in its ctx
        loc = f"{loc}.{first['ctx']['key']}" if loc else first["ctx"]["key"]
    if first["type"] == "extra_forbidden":
        msg = _unknown_key(loc_parts) or "unknown key" + _close_key(loc_parts)
    return f"{loc or 'config'}: {msg}"


def _unknown_key(loc: tuple) -> str | None:
    """A key the chosen kind of a tagged section does not have. When it is another kind's key
    (``--set operator.kind=damper`` on a hand operator leaves the hand's keys behind), what to
    do instead."""
    if len(loc) < 3 or not _is_union_tag(loc[-2], loc[-3]):
        return None
    section, kind, key = loc[-3], loc[-2], loc[-1]
    kinds = _KINDS["operator" if section == "operator" else "environment"]
    keys = [k for k in kinds[kind].model_fields if k != "kind"]
    where = "operator" if section == "operator" else f"environment.{section}"
    msg = f"unknown key for {where} kind {kind!r} (its keys: {', '.join(keys)})"
    if any(key in cls.model_fields for other, cls in kinds.items() if other != kind):
        # the kind's own keys (those every kind has, the operator's clutch and absent, stay)
        own = [k for k in keys if not all(k in cls.model_fields for cls in kinds.values())]
        example = ", ".join([f"kind: {kind}", *(f"{k}: ..." for k in own)])
        msg += (
            f"; changing the kind with --set leaves the other kind's keys behind: give the "
            f"whole section instead, --set '{where}={{{example}}}'"
        )
    return msg


def _close_key(loc: tuple) -> str:
    """'; did you mean 'delay_ms'?' when a key of that section is close to the one typed (a
    typo), else nothing: a suggestion far from what was typed only misleads."""
    import difflib

    section: Any = SessionConfig
    for i, part in enumerate(loc[:-1]):
        if isinstance(part, int) or _is_member_tag(part):
            continue
        if _is_union_tag(part, loc[i - 1] if i else None):
            section = _KINDS["operator" if loc[i - 1] == "operator" else "environment"][part]
            continue
        is_model = isinstance(section, type) and issubclass(section, BaseModel)
        field = section.model_fields.get(part) if is_model else None
        models = [t for t in annotation_leaves(field.annotation) if isinstance(t, type)
                  and issubclass(t, BaseModel)] if field else []  # fmt: skip
        if len(models) != 1:
            return ""
        section = models[0]
    close = difflib.get_close_matches(str(loc[-1]), list(section.model_fields), n=1, cutoff=0.75)
    return f"; did you mean {close[0]!r}?" if close else ""


_UNION_TAGS = {"damper", "hand", "wall", "foam", "spring", "mass"}
_KINDS: dict[str, dict[str, type[BaseModel]]] = {
    "operator": {"damper": DamperOperatorSpec, "hand": HandOperatorSpec},
    "environment": {
        "wall": WallSpec,
        "foam": WallSpec,
        "spring": SpringSpec,
        "damper": SpringSpec,
        "mass": MassSpec,
    },  # fmt: skip
}


_SHAPE_ERRORS = {"float_type", "list_type"}


def _is_member_tag(part: Any) -> bool:
    # A per-joint value is ``number | list of numbers``; pydantic names the member it tried
    # ('constrained-float', 'list[constrained-float]') in the location. No key looks like that.
    return isinstance(part, str) and not part.isidentifier()


def _pick_error(errors: list[Any]) -> Any:
    """The first error, unless it only says the input has the other shape of a per-joint union
    (a list where a number was tried): then the error of the member that fits the shape."""
    first = errors[0]
    tags = [i for i, p in enumerate(first["loc"]) if _is_member_tag(p)]
    if first["type"] in _SHAPE_ERRORS and tags:
        prefix = first["loc"][: tags[-1]]
        for other in errors[1:]:
            if other["loc"][: len(prefix)] == prefix and other["type"] not in _SHAPE_ERRORS:
                return other
    return first


def _is_union_tag(part: Any, previous: Any) -> bool:
    # pydantic puts the chosen member of a tagged union (operator.kind, environment.N.kind)
    # into the error location; a user never wrote that level, so it is left out.
    return part in _UNION_TAGS and (previous == "operator" or isinstance(previous, int))


def from_dict(data: Any, base_dir: Path | None = None) -> SessionConfig:
    """Validate a plain mapping; raise ConfigError with one line naming the offending key."""
    if not isinstance(data, dict):
        raise ConfigError(f"config: expected a mapping at the top level, got {type(data).__name__}")
    try:
        cfg = SessionConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_error(err)) from None
    return _resolve_paths(cfg, base_dir) if base_dir is not None else cfg


def _resolve_paths(cfg: SessionConfig, base_dir: Path) -> SessionConfig:
    sides: dict[str, BaseModel] = {}  # the sections to replace
    for side in ("hsi", "to"):
        spec: SideSpec = getattr(cfg, side)
        if spec.robot.urdf is not None and not spec.robot.urdf.is_absolute():
            robot = spec.robot.model_copy(update={"urdf": (base_dir / spec.robot.urdf).resolve()})
            sides[side] = spec.model_copy(update={"robot": robot})
    if cfg.can is not None:  # drive EDS files, like the URDFs
        sides["can"] = cfg.can.with_paths_resolved(base_dir)
    tls = cfg.link.zenoh.tls
    if tls is not None:  # certificates too

        def at(p: Path) -> Path:
            return p if p.is_absolute() else (base_dir / p).resolve()

        files = {s: TlsFiles(certificate=at(f.certificate), private_key=at(f.private_key))
                 for s, f in (("hsi", tls.hsi), ("to", tls.to))}  # fmt: skip
        tls = TlsSpec(root_ca=at(tls.root_ca), **files)
        zenoh = cfg.link.zenoh.model_copy(update={"tls": tls})
        sides["link"] = cfg.link.model_copy(update={"zenoh": zenoh})
    if cfg.link.impairment is not None:  # a trace file, like the URDFs
        link = sides.get("link", cfg.link)
        assert isinstance(link, LinkSpec)
        impairment = cfg.link.impairment.with_paths_resolved(base_dir)
        sides["link"] = link.model_copy(update={"impairment": impairment})
    return cfg.model_copy(update=sides)


def read_yaml(path: Path) -> Any:
    """Read a YAML file safely (a regular file only, bounded size, no object tags, no alias
    bombs, no duplicate keys)."""
    if file_problem(path) == "no such file":
        raise ConfigError(f"{shown(path)}: no such config file")
    return parse_yaml(read_bounded(path, MAX_CONFIG_BYTES, "config "), shown(path))


def parse_yaml(raw: bytes, where: str) -> Any:
    """Parse config YAML (``where`` names its source in the errors: a file, a log attachment)."""
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{where}: config larger than {MAX_CONFIG_BYTES} bytes")
    try:
        data = yaml.load(raw, Loader=_NoAliasLoader)  # noqa: S506 - SafeLoader subclass
    except RecursionError:
        raise ConfigError(f"{where}: not valid YAML: nested too deeply") from None
    except ValueError as err:  # a scalar YAML resolves but Python cannot convert
        raise ConfigError(f"{where}: not valid YAML: {_value_problem(err)}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{where}: not valid YAML{line}: {problem}") from None
    if data is None:
        raise ConfigError(f"{where}: the config is empty")
    return data


def _value_problem(err: ValueError) -> str:
    """What YAML's scalar conversion (int, timestamp) refused, without Python's advice."""
    text = str(err)
    if "integer string conversion" in text:
        return f"an integer too long to read ({text.rsplit(': ', 1)[-1].split(';')[0]})"
    return text


class _NoAliasLoader(yaml.SafeLoader):
    """SafeLoader that refuses anchors/aliases (a config never needs them and they enable
    exponential 'billion laughs' expansion) and repeated keys."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.YAMLError(
                f"YAML aliases (*{event.anchor}) are not allowed in a config "
                f"(line {event.start_mark.line + 1})"
            )
        return super().compose_node(parent, index)

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        # YAML's last-wins for a repeated key would silently drop a value the user wrote
        lines: dict[Any, int] = {}
        for key_node, _ in getattr(node, "value", ()):
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            try:
                first = lines.get(key)
            except TypeError:  # an unhashable key: SafeLoader says so
                continue
            if first is not None:
                where = f"line {line} twice" if first == line else f"lines {first} and {line}"
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} ({where})", key_node.start_mark
                )
            lines[key] = line
        return super().construct_mapping(node, deep=deep)


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``key.sub=value`` overrides (value parsed as YAML) to a raw config mapping.

    List items are addressed by index (``environment.0.stiffness_n_per_m=5000``).
    """
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected key=value")
        try:
            value = yaml.load(text, Loader=_NoAliasLoader)  # noqa: S506 - SafeLoader subclass
        except yaml.YAMLError as err:
            problem = getattr(err, "problem", None)
            why = f": {problem}" if problem else ""
            raise ConfigError(f"--set {key}: value {quote(text)} is not valid YAML{why}") from None
        except RecursionError:
            raise ConfigError(f"--set {key}: value {quote(text)} is not valid YAML") from None
        except ValueError as err:
            raise ConfigError(f"--set {key}: value {quote(text)}: {_value_problem(err)}") from None
        node: Any = data
        parts = key.split(".")
        for depth, part in enumerate(parts):
            last = depth == len(parts) - 1
            where = ".".join(parts[: depth + 1])
            if isinstance(node, list):
                if not part.isdecimal() or int(part) >= len(node):
                    raise ConfigError(f"--set {key}: {where} is not an index of the list")
                idx: Any = int(part)
            elif isinstance(node, dict):
                idx = part
                if not last and idx not in node:
                    node[idx] = {}
            else:
                raise ConfigError(f"--set {key}: {'.'.join(parts[:depth])} is not a section")
            if last:
                node[idx] = value
            else:
                node = node[idx]
    return data


def load(path: str | Path, overrides: list[str] | None = None) -> SessionConfig:
    """Load, override and validate a session config file."""
    path = Path(path)
    data = read_yaml(path)
    if not isinstance(data, dict):  # named here: from_dict cannot tell which file it was
        raise ConfigError(
            f"{shown(path)}: expected a mapping at the top level, got {type(data).__name__}"
        )
    if overrides:
        data = apply_overrides(data, overrides)
    return from_dict(data, base_dir=path.resolve().parent)


@overload
def per_joint(value: float | list[float], n: int, key: str) -> list[float]: ...
@overload
def per_joint(value: None, n: int, key: str) -> None: ...
@overload
def per_joint(value: float | list[float] | None, n: int, key: str) -> list[float] | None: ...
def per_joint(value: float | list[float] | None, n: int, key: str) -> list[float] | None:
    """Broadcast a per-joint parameter to n joints; ConfigError naming key on a length mismatch."""
    if value is None:
        return None
    if isinstance(value, list):
        if len(value) != n:
            raise ConfigError(f"{key}: has {len(value)} entries but the robot has {n} joints")
        return [float(v) for v in value]
    return [float(value)] * n
