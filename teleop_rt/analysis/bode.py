"""Measured displayed impedance: the project's own blocks in the paper's open chain, at 1 kHz.

``OpenChain`` wires what a session runs (two ``SimBackend`` plants, ``ComputedTorque``, ``Pid``
C1 and C2, ``WaveChannel``) as the paper's open chain (Fig 2 cut at omega_o): the operator
velocity omega_o is imposed on the channel's HSI port (omega_c = omega_o), a damper operator
``JointDamperOperator`` (Z_o) loads the HSI, a joint-space environment (``JointSpringDamper``
and, for Z_e = m s, ``world.JointMass``) loads the TO, and tau_h (the torque the operator applies to
the HSI) is measured. Only one joint is excited; computed torque keeps the others at rest.
The plants integrate with semi-implicit Euler and one sub-step (the discrete model assumes it).

``measure_displayed_impedance`` drives a sine per frequency and estimates Z_h = tau_h / omega_o
by lock-in over windows of whole drive periods that are also whole multiples of the channel's
round trip of 4 D ticks (a lossless channel keeps startup echoes of period 4 D forever; over such
windows they do not leak into the estimate). For that the frequency is moved to the nearest one
whose period fits (by at most ``snap_tol``, 1 %); the frequencies actually measured are returned.

Settledness: the chain can ring up (a velocity-controlled TO against a spring has Re Z_t < 0 at
some frequencies, and with delay the wave reflections grow), or have echo modes that decay over
tens of seconds. A frequency counts as settled only when

* no monitored signal (tau_h, HSI and TO velocity, tau_e) grows: the part of each signal that
  is neither its mean nor its drive-frequency sine must not be larger (by ``growth_tol``) than
  in the window before;
* two consecutive windows give estimates that differ by at most ``settle_tol`` (relative); and
* the transient still in the estimate, extrapolated from that change with the slowest mode of
  the exact discrete model (``discrete.window_decay``: r = |z|^N per window, at most
  r / (1 - r) times the change), is at most ``settle_tol`` too. Two windows that agree while a
  mode decays by only 1 % per window say little: without this test such a point passed with
  0.12 % error. A mode that never decays (r >= 1: a marginal or unstable chain) fails it always.

Otherwise more windows are run, up to ``max_seconds`` of simulated time (at least the settling
time and three windows); a frequency that never qualifies, or whose signals blow up, is reported
as not settled, with no number (NaN here, null in JSON), and a reason: "changing", "growing",
"diverged", "slow" (the extrapolated transient stays above ``settle_tol``) or "marginal" (a mode
of the model does not decay). The model's modes are those of the linear chain; with friction
not compensated (``chain_kwargs``) they are an approximation.

Z_e = m s: a mass cannot be measured without a lag on a sampled robot (its torque m a during
[k, k+1] depends on the command computed from that very measurement), so ``JointMass`` applies
and reports tau = m (v[k] - v[k-1]) / dt, the mass's torque over the last tick: what a sensor
sampled at tick start reads of a rigid payload. The plant then feels exactly what the computed
torque cancels (the chain stays linear and decoupled) and Z_e(z) = m (1 - 1/z) / dt, the
backward difference that the joint spring's position also uses. Behind a delay this explicit
mass rings up once m c2 / (M2 b) nears 1 (m ~ 0.01 kg m^2 with the paper's gains and the 30 Hz
filter; without the filter any mass or spring behind a delay rings); such frequencies are
reported as not settled.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from teleop_rt.analysis.discrete import (
    DT,
    continuous_params,
    delay_ticks,
    displayed_impedance_z,
    window_decay,
)
from teleop_rt.analysis.impedance import (
    AnalysisParamError,
    ControllerGains,
    ImpedanceParams,
    displayed_impedance,
)
from teleop_rt.com.channel import make_ports
from teleop_rt.com.link import InProcessLink
from teleop_rt.config import ControllerSpec, DamperOperatorSpec, RobotSpec, SafetySpec
from teleop_rt.control import ComputedTorque, Pid
from teleop_rt.errors import SafetyStop
from teleop_rt.hal.sim import SimBackend, initial_configuration
from teleop_rt.model import RobotModel
from teleop_rt.safety import RobotGuard
from teleop_rt.site import HsiSite, ToSite
from teleop_rt.world import JointDamperOperator, JointMass, JointSpringDamper, Load

SCARA_URDF = Path(__file__).resolve().parents[2] / "robots" / "urdf" / "scara_2dof.urdf"
SCARA_Q0 = [-0.8, 1.8]


def default_robot() -> RobotSpec:
    """The project's SCARA (robots/urdf/scara_2dof.urdf) at q0 = (-0.8, 1.8) rad."""
    return RobotSpec(urdf=SCARA_URDF, ee_frame="tool", q0_rad=SCARA_Q0)


def default_omegas(omega_min: float = 0.5, omega_max: float = 50.0, points: int = 20) -> np.ndarray:
    """``points`` log-spaced frequencies from omega_min to omega_max, rad/s."""
    return np.geomspace(omega_min, omega_max, points)


def controller_spec(c: ControllerGains | float) -> ControllerSpec:
    """The ``Pid`` config of analytic gains (P if only kp, else PID; no limits)."""
    g = c if isinstance(c, ControllerGains) else ControllerGains(kp=float(c))
    kind: Literal["p", "pid"] = "pid" if (g.ki or g.kd) else "p"
    return ControllerSpec(
        kind=kind, kp=g.kp, ki=g.ki, kd=g.kd, derivative_filter_s=g.derivative_filter_s
    )


@dataclass
class ChainRecord:
    """Signals of the excited joint over a run, one sample per tick (SI)."""

    omega_o: np.ndarray  # imposed operator velocity, rad/s
    tau_h: np.ndarray  # torque the operator applies to the HSI, N m
    v_h: np.ndarray  # HSI velocity, rad/s
    v_t: np.ndarray  # TO velocity, rad/s
    tau_e: np.ndarray  # torque the TO applies to the environment, N m


class OpenChain:
    """The paper's open chain on the project's blocks; ``run`` advances it tick by tick.

    params: the chain (its ``delay_model`` is irrelevant: the delay is delay_s / dt whole
    ticks). joint: the excited joint (0-based). Robots default to the SCARA; every joint gets
    the same virtual masses, gains, b, Z_o and environment. ``compensate_friction``: per side,
    as a session's computed torque (the model is exact only when the plant friction is
    compensated, the default).
    """

    def __init__(
        self,
        params: ImpedanceParams,
        joint: int = 1,
        dt: float = DT,
        hsi_robot: RobotSpec | None = None,
        to_robot: RobotSpec | None = None,
        compensate_friction: tuple[bool, bool] = (True, True),
        coulomb_smoothing_rad_s: float = 0.01,
    ) -> None:
        p = params
        self.params, self.dt, self.joint = p, dt, joint
        self.delay_ticks = delay_ticks(p.delay_s, dt)
        hsi_robot = hsi_robot or default_robot()
        to_robot = to_robot or default_robot()
        smooth = coulomb_smoothing_rad_s
        plant_h = RobotModel.from_spec(hsi_robot, "hsi", smooth)
        plant_t = RobotModel.from_spec(to_robot, "to", smooth)
        n = plant_h.nv
        if plant_t.nv != n:
            raise AnalysisParamError(f"HSI has {n} joints but TO has {plant_t.nv}")
        if not 0 <= joint < n:
            raise AnalysisParamError(f"joint {joint} does not exist (the robots have {n}: 0..)")
        self.n = n
        q0_h = initial_configuration(hsi_robot.q0_rad, plant_h, "hsi")
        q0_t = initial_configuration(to_robot.q0_rad, plant_t, "to")
        self.q0_h, self.q0_t = q0_h.tolist(), q0_t.tolist()
        operator = JointDamperOperator(
            DamperOperatorSpec(kind="damper", damping_nm_s_per_rad=p.z_o), n
        )
        env: list[Load] = [
            JointSpringDamper([p.env_stiffness] * n, [p.env_damping] * n, self.q0_t)
        ]
        if p.env_mass:
            env.append(JointMass([p.env_mass] * n, dt))
        # the sites a session runs (the same kernels: the control law is wired once), on
        # parameters instead of a config; safety off: only non-finite values stop the chain
        ctrl_h = RobotModel.from_spec(hsi_robot, "h", smooth)
        ctrl_t = RobotModel.from_spec(to_robot, "t", smooth)
        no_checks = SafetySpec(enabled=False)
        port_h, port_t = make_ports("wave", [p.b] * n, self.delay_ticks, dt, p.wave_filter_hz)
        self.hsi = HsiSite.from_parts(
            ctrl_h, SimBackend(plant_h, [operator], q0_h, dt),
            Pid(controller_spec(p.c1), n, dt, "c1"),
            ComputedTorque(ctrl_h, [p.m1] * n, compensate_friction[0]),
            RobotGuard(no_checks, ctrl_h, "hsi", dt), port_h, dt,
        )  # fmt: skip
        self.to = ToSite.from_parts(
            ctrl_t, SimBackend(plant_t, env, q0_t, dt),
            Pid(controller_spec(p.c2), n, dt, "c2"),
            ComputedTorque(ctrl_t, [p.m2] * n, compensate_friction[1]),
            RobotGuard(no_checks, ctrl_t, "to", dt), port_t, dt,
        )  # fmt: skip
        for site in (self.hsi, self.to):  # an analysis imposes what it likes: no bounds
            site.guard.tau_ext_max[:] = site.guard.v_measured_max[:] = math.inf
        self.link = InProcessLink(n, self.delay_ticks)
        self.tick = 0
        self.other_joint_motion = 0.0  # max |q - q0| of the joints not excited, both robots

    def run(self, omega_o: np.ndarray | Sequence[float]) -> ChainRecord:
        """Impose omega_o[i] on the excited joint for len(omega_o) ticks; record the signals.

        Each tick is the sites' own (``Site.sense``, ``Site.update``) with one change: the
        HSI port's flow is the imposed operator velocity instead of the HSI's (the chain is
        cut at omega_o, Fig 2). A non-finite signal ends the chain with ``SafetyStop``."""
        w_list = np.asarray(omega_o, dtype=float).tolist()
        ticks = len(w_list)
        tau_h, v_h, v_t, tau_e = ([0.0] * ticks for _ in range(4))
        n, j, link = self.n, self.joint, self.link
        others = [i for i in range(n) if i != j]
        hsi, to = self.hsi, self.to
        flow, sent = hsi.port.flow, hsi.tx.x
        th, te = hsi.signals.tau, to.signals.tau
        fb_h, fb_t = hsi.feedback, to.feedback
        q0_h, q0_t, other = self.q0_h, self.q0_t, self.other_joint_motion
        for k in range(ticks):
            hsi.sense(link)
            flow[:] = 0.0
            flow[j] = w_list[k]
            sent[:] = flow
            to.sense(link)
            tau_h[k], v_h[k], v_t[k], tau_e[k] = th[j], fb_h.v[j], fb_t.v[j], te[j]
            for i in others:
                other = max(other, abs(fb_h.q[i] - q0_h[i]), abs(fb_t.q[i] - q0_t[i]))
            hsi.update(link)
            to.update(link)
        self.tick += ticks
        self.other_joint_motion = other
        arr = np.asarray
        return ChainRecord(arr(w_list), arr(tau_h), arr(v_h), arr(v_t), arr(tau_e))


# --- frequency response -----------------------------------------------------------------------
@dataclass
class PointResult:
    """One frequency: what was measured and how it settled."""

    omega_requested: float
    omega: float  # the frequency measured (whole periods in whole round trips), rad/s
    z: complex  # measured Z_h, N m s/rad (nan + nan j if not settled)
    settled: bool
    window_ticks: int
    simulated_s: float  # simulated time spent on this frequency
    relative_change: float  # between the last two windows (inf if fewer than two)
    reason: str  # "settled", "changing", "growing", "diverged", "slow", "marginal"
    error_bound: float = math.inf  # extrapolated relative transient left in z (module doc)


@dataclass
class BodeResult:
    """A sweep: measured, exact discrete-time and continuous-time Z_h at the measured omegas."""

    params: ImpedanceParams
    joint: int
    amplitude_rad_s: float
    dt: float
    points: list[PointResult]
    settings: dict = field(default_factory=dict)

    @property
    def omega(self) -> np.ndarray:
        return np.array([pt.omega for pt in self.points])

    @property
    def measured(self) -> np.ndarray:
        return np.array([pt.z for pt in self.points], dtype=complex)

    @property
    def settled(self) -> np.ndarray:
        return np.array([pt.settled for pt in self.points], dtype=bool)

    @property
    def analytic(self) -> np.ndarray:
        """Continuous-time Z_h (eq 20, exact delay, wave filter at its matched cut-off) at the
        measured frequencies (``discrete.continuous_params``)."""
        return displayed_impedance(1j * self.omega, continuous_params(self.params, self.dt))

    @property
    def discrete(self) -> np.ndarray:
        """Exact discrete-time Z_h (teleop_rt.analysis.discrete) at the measured frequencies."""
        return displayed_impedance_z(self.omega, self.params, self.dt)

    def to_dict(self, params: dict | None = None) -> dict:
        """The JSON document of ``teleop-rt bode`` (null for unsettled measurements)."""
        meas, ok = self.measured, self.settled
        ana, dis = self.analytic, self.discrete

        def parts(z: np.ndarray, mask: np.ndarray | None = None) -> dict:
            keep = np.ones(len(z), bool) if mask is None else mask
            return {
                "re": [float(x.real) if m else None for x, m in zip(z, keep, strict=True)],
                "im": [float(x.imag) if m else None for x, m in zip(z, keep, strict=True)],
            }

        return {
            "params": params if params is not None else self.params_dict(),
            "omega_rad_s": [float(w) for w in self.omega],
            "analytic": parts(ana),
            "measured": {**parts(meas, ok), "settled": [bool(x) for x in ok]},
            "discrete": parts(dis),
        }

    def params_dict(self) -> dict:
        """Every parameter of the analysis and the measurement, SI units."""
        return {
            **impedance_params_dict(self.params),
            # the analytic model's cut-off: the sampled filter's DC group delay (null: no filter)
            "wave_filter_matched_hz": continuous_params(self.params, self.dt).wave_filter_hz,
            "dt_s": self.dt,
            "delay_ticks": delay_ticks(self.params.delay_s, self.dt),
            "joint": self.joint,
            "amplitude_rad_s": self.amplitude_rad_s,
            "omega_requested_rad_s": [pt.omega_requested for pt in self.points],
            **self.settings,
        }


def _gains_dict(c: ControllerGains | float) -> dict:
    g = c if isinstance(c, ControllerGains) else ControllerGains(kp=float(c))
    return {"kp": g.kp, "ki": g.ki, "kd": g.kd, "derivative_filter_s": g.derivative_filter_s}


def impedance_params_dict(p: ImpedanceParams) -> dict:
    """The chain's parameters with SI unit suffixes."""
    return {
        "m1_kg_m2": p.m1,
        "m2_kg_m2": p.m2,
        "c1": _gains_dict(p.c1),
        "c2": _gains_dict(p.c2),
        "z_o_nm_s_per_rad": p.z_o,
        "b_nm_s_per_rad": p.b,
        "delay_s": p.delay_s,
        "wave_filter_hz": p.wave_filter_hz,
        "env_mass_kg_m2": p.env_mass,
        "env_damping_nm_s_per_rad": p.env_damping,
        "env_stiffness_nm_per_rad": p.env_stiffness,
        "analytic_delay_model": "exact",
    }


def choose_window(
    omega: float,
    dt: float,
    round_trip_ticks: int,
    periods: float,
    min_ticks: int,
    max_ticks: int,
    snap_tol: float = 0.01,
) -> tuple[float, int, int]:
    """(omega', N, P): a window of N ticks, a multiple of ``round_trip_ticks`` (>= 1), holding
    exactly P >= ``periods`` periods of omega' = 2 pi P / (N dt). The first P (from the fewest)
    with |omega'/omega - 1| <= snap_tol and N >= min_ticks is taken; if none fits in max_ticks,
    the closest found."""
    period = 2.0 * math.pi / (omega * dt)  # ticks
    if period <= 2.0:
        raise AnalysisParamError(
            f"omega {omega:g} rad/s is not below the Nyquist frequency {math.pi / dt:g} rad/s"
        )
    step = max(round_trip_ticks, 1)
    best: tuple[float, int, int] | None = None
    p = max(1, math.ceil(periods))
    while True:
        n_ticks = step * max(1, round(p * period / step))
        if n_ticks >= min_ticks and 2 * p < n_ticks:
            err = abs(p * period / n_ticks - 1.0)
            if best is None or err < best[0]:
                best = (err, n_ticks, p)
            if err <= snap_tol:
                break
        if n_ticks >= max_ticks and best is not None:
            break
        p += 1
    _, n_ticks, p = best
    return 2.0 * math.pi * p / (n_ticks * dt), n_ticks, p


def _lock_in(x: np.ndarray, basis: np.ndarray) -> complex:
    return complex(x @ basis)


def _residual_rms(x: np.ndarray, basis: np.ndarray) -> float:
    """RMS of x minus its mean and its drive-frequency sine (whole periods in the window)."""
    n = len(x)
    c = 2.0 / n * (x @ basis)
    r = x - x.mean() - (c * basis.conj()).real
    return float(np.sqrt(np.mean(r * r)))


def measure_point(
    params: ImpedanceParams,
    omega: float,
    joint: int = 1,
    amplitude_rad_s: float = 0.05,
    settle_periods: float = 1.0,
    measure_periods: float = 2.0,
    dt: float = DT,
    *,
    min_settle_s: float = 1.0,
    min_window_s: float = 0.5,
    max_seconds: float = 60.0,
    settle_tol: float = 1e-4,
    growth_tol: float = 1e-3,
    snap_tol: float = 0.01,
    chain_kwargs: dict | None = None,
) -> PointResult:
    """Measure Z_h at (about) omega rad/s on a fresh chain; see the module doc for the rules."""
    d = delay_ticks(params.delay_s, dt)
    max_ticks = max(1, round(max_seconds / dt))
    w, n_win, _ = choose_window(
        omega, dt, 4 * d, measure_periods, round(min_window_s / dt), max_ticks // 2, snap_tol
    )
    chain = OpenChain(params, joint, dt, **(chain_kwargs or {}))
    period_ticks = 2.0 * math.pi / (w * dt)
    n_settle = max(round(settle_periods * period_ticks), round(min_settle_s / dt))
    max_ticks = max(max_ticks, n_settle + 3 * n_win)  # always room for three windows
    # a blow-up bound far above any settled response of this chain to this drive
    scale = 1.0 + params.b + params.z_o + params.env_damping
    limit = 1e6 * amplitude_rad_s * (scale + params.env_stiffness / w + params.env_mass * w)
    if run_bounded(chain, amplitude_rad_s * np.sin(w * dt * np.arange(n_settle)), limit) is None:
        return _unsettled(omega, w, n_win, chain.tick * dt, math.inf, "diverged", math.inf)
    z_prev: complex | None = None
    res_prev: list[float] = []
    rel = bound = math.inf
    reason = "changing"
    z_floor = 1e-12 * params.b
    tail = _tail_factor(window_decay(params, n_win, dt))
    while True:
        k = np.arange(chain.tick, chain.tick + n_win)
        basis = np.exp(-1j * w * dt * k)
        w_o = amplitude_rad_s * np.sin(w * dt * k)
        rec = run_bounded(chain, w_o, limit)
        if rec is None:
            reason = "diverged"
            break
        z = _lock_in(rec.tau_h, basis) / _lock_in(rec.omega_o, basis)
        signals = (rec.tau_h, rec.v_h, rec.v_t, rec.tau_e)
        res = [_residual_rms(x, basis) for x in signals]
        if z_prev is not None:
            rel = abs(z - z_prev) / max(abs(z), z_floor)
            growing = any(
                r > rp * (1.0 + growth_tol) + 1e-9 * float(np.abs(x).max())
                for r, rp, x in zip(res, res_prev, signals, strict=True)
            )
            bound = rel * tail if rel > 0 else 0.0  # (0 * inf: nothing left to extrapolate)
            reason = _verdict(growing, rel, bound, tail, settle_tol)
            if reason == "settled":
                seconds = chain.tick * dt
                return PointResult(omega, w, z, True, n_win, seconds, rel, reason, bound)
        z_prev, res_prev = z, res
        if chain.tick + n_win > max_ticks:
            break
    return _unsettled(omega, w, n_win, chain.tick * dt, rel, reason, bound)


def _tail_factor(r: float) -> float:
    """Bound on (transient left) / (last change) for a per-window decay r (discrete module doc);
    at least 1, inf when a mode does not decay."""
    return math.inf if r >= 1.0 else max(1.0, r / (1.0 - r))


def _verdict(growing: bool, rel: float, bound: float, tail: float, settle_tol: float) -> str:
    """The reason of one window's test (module doc), "settled" if it passes."""
    if growing:
        return "growing"
    if rel > settle_tol:
        return "changing"
    if bound <= settle_tol and math.isfinite(tail):
        return "settled"
    return "marginal" if math.isinf(tail) else "slow"


def _unsettled(
    omega: float, w: float, n_win: int, seconds: float, rel: float, reason: str, bound: float
) -> PointResult:
    nan = complex(math.nan, math.nan)
    return PointResult(omega, w, nan, False, n_win, seconds, rel, reason, bound)


def run_bounded(
    chain: OpenChain, omega_o: np.ndarray, limit: float, chunk: int = 200
) -> ChainRecord | None:
    """``chain.run(omega_o)`` in chunks; None as soon as a signal exceeds limit or is not finite
    (a chain ringing up is stopped before its numbers overflow)."""
    parts = []
    with np.errstate(over="ignore", invalid="ignore"):
        for start in range(0, len(omega_o), chunk):
            try:
                rec = chain.run(omega_o[start : start + chunk])
            except SafetyStop:  # a signal went non-finite: rung up
                return None
            for x in (rec.tau_h, rec.v_h, rec.v_t, rec.tau_e):
                if not float(np.abs(x).max()) <= limit:  # also catches nan
                    return None
            parts.append(rec)
    if len(parts) == 1:
        return parts[0]
    return ChainRecord(
        *(np.concatenate([getattr(r, f) for r in parts]) for f in ChainRecord.__dataclass_fields__)
    )


# The work per frequency is at least the settling time and three windows, whatever
# --max-seconds says; beyond this much simulated time (an hour: minutes of computing, a window's
# arrays of about 100 MB) a frequency is refused before anything is allocated.
MAX_POINT_SECONDS = 3600.0


def point_seconds(
    omega: float,
    settle_periods: float = 1.0,
    measure_periods: float = 2.0,
    min_settle_s: float = 1.0,
    min_window_s: float = 0.5,
) -> float:
    """The least simulated time ``measure_point`` spends on omega: the settling time and three
    windows (before a window's length is rounded to the channel's round trip)."""
    period = 2.0 * math.pi / omega
    settle = max(settle_periods * period, min_settle_s)
    return settle + 3.0 * max(measure_periods * period, min_window_s)


def measure_displayed_impedance(
    params: ImpedanceParams,
    omegas: Sequence[float] | np.ndarray | None = None,
    joint: int = 1,
    amplitude_rad_s: float = 0.05,
    settle_periods: float = 1.0,
    measure_periods: float = 2.0,
    dt: float = DT,
    *,
    progress: Callable[[int, int], None] | None = None,
    **options,
) -> BodeResult:
    """Measured Z_h = tau_h / omega_o of the running blocks, one fresh chain per frequency.

    params: the chain (``ImpedanceParams``; env_mass, env_damping, env_stiffness make the
    joint-space environment). omegas: rad/s (default: 20 log-spaced from 0.5 to 50); each is
    moved by at most 1 % to fit the lock-in window (``BodeResult.omega`` holds what was
    measured). joint: the excited joint, 0-based. amplitude_rad_s: of the imposed omega_o.
    settle_periods / measure_periods: drive periods before the first window / per window
    (at least ``min_settle_s`` = 1 s and ``min_window_s`` = 0.5 s). Further keyword options go
    to ``measure_point`` (tolerances, ``max_seconds`` per frequency, ``chain_kwargs`` for
    ``OpenChain``: robots, friction compensation). progress(done, total) after each frequency.
    """
    if not 0 < amplitude_rad_s < math.inf:
        raise AnalysisParamError(f"amplitude must be > 0 rad/s and finite, got {amplitude_rad_s}")
    omegas = default_omegas() if omegas is None else np.asarray(omegas, dtype=float)
    if len(omegas) == 0 or not np.all(omegas > 0):
        raise AnalysisParamError("frequencies must be > 0 rad/s (and at least one)")
    if np.any(omegas * dt >= math.pi / 1.01):
        raise AnalysisParamError(
            f"frequencies must stay below the Nyquist frequency {math.pi / dt:g} rad/s "
            f"(with 1 % room to fit the window), got {omegas.max():g}"
        )
    delay_ticks(params.delay_s, dt)
    minima = {k: v for k, v in options.items() if k in ("min_settle_s", "min_window_s")}
    for omega in omegas:  # before any work: the arrays of one window are sized by it
        need = point_seconds(float(omega), settle_periods, measure_periods, **minima)
        if need > MAX_POINT_SECONDS:
            lowest = 2.0 * math.pi * (settle_periods + 3.0 * measure_periods) / MAX_POINT_SECONDS
            raise AnalysisParamError(
                f"frequency {omega:g} rad/s needs at least {need:.3g} s of simulated time "
                f"(settling and 3 windows of {measure_periods:g} periods), above the limit of "
                f"{MAX_POINT_SECONDS:g} s per frequency: the lowest is {lowest:.3g} rad/s"
            )
    points = []
    for i, omega in enumerate(omegas):
        pt = measure_point(
            params,
            float(omega),
            joint,
            amplitude_rad_s,
            settle_periods,
            measure_periods,
            dt,
            **options,
        )
        points.append(pt)
        if progress is not None:
            progress(i + 1, len(omegas))
    defaults = {
        name: par.default
        for name, par in inspect.signature(measure_point).parameters.items()
        if par.kind is inspect.Parameter.KEYWORD_ONLY and name != "chain_kwargs"
    }
    settings = {
        "settle_periods": settle_periods,
        "measure_periods": measure_periods,
        **defaults,
        **{k: v for k, v in options.items() if k != "chain_kwargs"},
    }
    return BodeResult(params, joint, amplitude_rad_s, dt, points, settings)


# --- plot -------------------------------------------------------------------------------------
def plot_bode(
    result: BodeResult, path: str | Path, title: str | None = None, force: bool = True
) -> None:
    """Magnitude and phase: continuous (line) and discrete (dashed) models, measured points,
    unsettled frequencies marked (red dotted lines). matplotlib, no display; the format from
    the extension, an existing file overwritten only with ``force`` (teleop_rt.output)."""
    from matplotlib.figure import Figure

    from teleop_rt.output import save_figure, wrap_title

    w = result.omega
    dense = np.geomspace(w.min() / 1.5, w.max() * 1.5, 300)
    dense = dense[dense * result.dt < math.pi]
    ana = displayed_impedance(1j * dense, continuous_params(result.params, result.dt))
    dis = displayed_impedance_z(dense, result.params, result.dt)
    meas, ok = result.measured, result.settled
    fig = Figure(figsize=(8, 6.5), layout="constrained")
    ax_m = fig.add_subplot(2, 1, 1)
    ax_p = fig.add_subplot(2, 1, 2, sharex=ax_m)
    continuous = continuous_label(result.params, result.dt)
    for ax, f, label in ((ax_m, np.abs, "|Z_h| (N m s/rad)"), (ax_p, _phase_deg, "phase (deg)")):
        ax.plot(dense, f(ana), "-", color="C0", label=continuous)
        ax.plot(dense, f(dis), "--", color="C1", label="discrete (1 kHz, exact)")
        if ok.any():
            ax.plot(w[ok], f(meas[ok]), "o", color="k", mfc="none", label="measured")
        for i, x in enumerate(w[~ok]):
            ax.axvline(x, color="red", ls=":", label="not settled" if i == 0 else None)
        ax.set_xscale("log")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    ax_m.set_yscale("log")
    ax_p.set_xlabel("omega (rad/s)")
    ax_m.legend(loc="best", fontsize="small")
    p = result.params
    text = (
        title
        or f"displayed impedance, joint {result.joint}: T_d = {p.delay_s * 1000:g} ms, "
        f"b = {p.b:g}, filter {_filter_text(p, result.dt)}, Z_e = {p.env_mass:g} s + "
        f"{p.env_damping:g} + {p.env_stiffness:g}/s"
    )
    fig.suptitle(wrap_title(text, fig.get_figwidth()))
    save_figure(fig, path, "--plot", force)


def continuous_label(p: ImpedanceParams, dt: float) -> str:
    """The continuous model's legend entry: it names the matched filter only when there is one
    (as the title's ``_filter_text`` does)."""
    filtered = continuous_params(p, dt).wave_filter_hz is not None
    return "continuous (eq 20, matched filter)" if filtered else "continuous (eq 20)"


def _filter_text(p: ImpedanceParams, dt: float) -> str:
    matched = continuous_params(p, dt).wave_filter_hz
    return "off" if matched is None else f"{p.wave_filter_hz:g} Hz (matched {matched:.1f} Hz)"


def _phase_deg(z: np.ndarray) -> np.ndarray:
    return np.degrees(np.angle(z))


# --- from a session config --------------------------------------------------------------------
DEFAULT_OPERATOR_DAMPING = 10.0  # N m s/rad, Z_o when the config's operator is not a damper


@dataclass
class BodeSetup:
    """What ``teleop-rt bode`` measures, taken from a session config."""

    params: ImpedanceParams
    dt: float
    chain_kwargs: dict
    info: dict  # where each value came from, for the JSON params


def _pick(value: float | list[float], joint: int, key: str) -> float:
    if isinstance(value, list):
        if joint >= len(value):
            raise AnalysisParamError(f"{key} has {len(value)} entries: there is no joint {joint}")
        return float(value[joint])
    return float(value)


def _gains_from_spec(spec: ControllerSpec, joint: int, key: str) -> ControllerGains:
    return ControllerGains(
        kp=_pick(spec.kp, joint, f"{key}.kp"),
        ki=_pick(spec.ki, joint, f"{key}.ki"),
        kd=_pick(spec.kd, joint, f"{key}.kd"),
        derivative_filter_s=spec.derivative_filter_s,
    )


def setup_from_config(
    cfg,
    joint: int = 1,
    env_mass: float = 0.0,
    env_damping: float = 0.0,
    env_stiffness: float = 0.0,
) -> BodeSetup:
    """The chain of a session config (``teleop_rt.config.SessionConfig``) for one joint.

    Virtual masses, controller gains, b, delay and wave filter come from the config; Z_o from
    ``operator.damping_nm_s_per_rad`` for a damper operator, else 10 N m s/rad; the environment
    (joint space) from the arguments, free space by default. The plants are simulated with
    semi-implicit Euler, one sub-step and no sensor noise whatever the config's plant section
    says, and controller limits are not applied (the analysis is linear); ``info`` says so.
    """
    if cfg.channel.mode != "wave":
        raise AnalysisParamError(
            f"bode analyses the wave channel; this config has channel.mode: {cfg.channel.mode}"
        )
    if joint < 0:
        raise AnalysisParamError(f"joint must be >= 0, got {joint}")
    op = cfg.operator
    if isinstance(op, DamperOperatorSpec):
        z_o = _pick(op.damping_nm_s_per_rad, joint, "operator.damping_nm_s_per_rad")
        z_o_source = "operator.damping_nm_s_per_rad"
    else:
        z_o = DEFAULT_OPERATOR_DAMPING
        z_o_source = f"default (operator kind {op.kind!r} is not a damper)"
    params = ImpedanceParams(
        m1=_pick(cfg.hsi.virtual_mass, joint, "hsi.virtual_mass"),
        m2=_pick(cfg.to.virtual_mass, joint, "to.virtual_mass"),
        c1=_gains_from_spec(cfg.hsi.controller, joint, "hsi.controller"),
        c2=_gains_from_spec(cfg.to.controller, joint, "to.controller"),
        z_o=z_o,
        b=_pick(cfg.channel.wave_impedance, joint, "channel.wave_impedance"),
        delay_s=cfg.delay_ticks * cfg.dt,
        env_mass=env_mass,
        env_damping=env_damping,
        env_stiffness=env_stiffness,
        # no received waves at zero delay: the channel couples directly, unfiltered
        wave_filter_hz=cfg.channel.wave_filter_hz if cfg.delay_ticks > 0 else None,
    )
    notes = []
    if cfg.plant.integrator != "semi_implicit_euler" or cfg.plant.substeps != 1:
        notes.append(
            f"config plant {cfg.plant.integrator} x{cfg.plant.substeps} replaced by "
            "semi_implicit_euler x1 (the discrete model's plant)"
        )
    if cfg.plant.torque_noise_std_nm or cfg.plant.velocity_noise_std_rad_s:
        notes.append("sensor noise of the config's plant not applied")
    for side in ("hsi", "to"):
        spec = getattr(cfg, side).controller
        if spec.integral_limit is not None or spec.output_limit is not None:
            notes.append(f"{side}.controller limits not applied (linear analysis)")
    compensate = (cfg.hsi.compensate_friction, cfg.to.compensate_friction)
    if not all(compensate):
        notes.append("friction not compensated on a side: the chain is not the linear model")
    chain_kwargs = {
        "hsi_robot": cfg.hsi.robot,
        "to_robot": cfg.to.robot,
        "compensate_friction": compensate,
        "coulomb_smoothing_rad_s": cfg.plant.coulomb_smoothing_rad_s,
    }
    info = {
        "z_o_source": z_o_source,
        "environment_source": "command line (joint space)",
        "hsi_urdf": str(cfg.hsi.robot.urdf or cfg.hsi.robot.example_robot),
        "to_urdf": str(cfg.to.robot.urdf or cfg.to.robot.example_robot),
        "hsi_q0_rad": cfg.hsi.robot.q0_rad,
        "to_q0_rad": cfg.to.robot.q0_rad,
        "compensate_friction": {"hsi": compensate[0], "to": compensate[1]},
        "coulomb_smoothing_rad_s": cfg.plant.coulomb_smoothing_rad_s,
        "plant": {"integrator": "semi_implicit_euler", "substeps": 1, "sensor_noise": False},
        "notes": notes,
    }
    return BodeSetup(params, cfg.dt, chain_kwargs, info)
