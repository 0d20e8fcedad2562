"""The workspace mapping at each site, between its robot and its port of the channel: motion
and force scaling, the clutch (indexing) and the operator's presence (dead-man), kept passive.

The channel (``teleop_rt.com.port``) is left as it is: its port variables are in the HSI's
units, and everything here is a map between a robot's own variables and its port's:

    HSI:  omega_c = r v_h                     rendered torque = r tau_c
    TO:   v_ref   = r alpha omega_t           tau_t = r beta tau_e

``alpha`` (``mapping.motion_scale``) is the TO's motion per HSI motion, ``beta``
(``mapping.force_scale``) the torque the HSI displays per TO torque (at steady state the
operator feels ``beta tau_e`` against a TO that moves ``alpha`` times as far). ``r`` in [0, 1]
is the coupling gain: 1 while coupled, 0 while the clutch is pressed or the operator is away,
ramped back up on re-engaging.

What is passive, exactly. Each site's map is a transformer (Paynter's bond-graph TF, here
time varying through r) times, at the TO, a constant power scale:

* HSI: ``omega_c tau_c = (r v_h) tau_c = v_h (r tau_c)``: the power into the channel's HSI
  port is the power the HSI robot receives from its rendered torque, at every tick and for any
  r(t), since flow and effort carry the same r of the same tick. Lossless.
* TO: ``omega_t tau_t = r beta omega_t tau_e = (beta / alpha) v_ref tau_e``: the power out of
  the channel's TO port is ``beta / alpha`` times the power the TO's velocity reference does
  on the environment. For ``beta = alpha`` this is a lossless transformer (a lever: TO motion
  scaled by alpha, force fed back scaled by alpha); otherwise it is a transformer of ratio
  alpha followed by a power gain ``kappa = beta / alpha``, which is Colgate's power scaling
  ("Robust impedance shaping telemanipulation", IEEE T-RA 1993): the channel sees the
  environment's impedance times kappa, which is passive exactly when the environment is
  (kappa > 0). Seen from the channel's TO port in the TO's own units the wave impedance is
  ``b / (alpha beta)`` (tau_e = tau_t / beta, v = alpha omega_t); Niemeyer and Slotine scale
  motion by choosing different wave impedances at the two ends (IEEE J. Oceanic Eng. 1991),
  which gives the lossless case only: the force gain beyond it is the power scale.

So the channel's energy (eq 7) stays the unchanged wave / TDPA channel's, >= 0, for any
alpha, beta > 0 and any clutch script; and the scaled two-port between the robots' ports,
``integral of v_h (r tau_c) - (beta / alpha) v_ref tau_e``, is that same energy, tick for
tick (tests/test_mapping.py checks both). What scaling does not preserve is the operator's
share of the environment's energy: an active environment's energy reaches the operator
multiplied by kappa.

Clutch and presence (``operator.clutch``, ``operator.absent`` in the config: scripted
intervals). Pressed, r = 0: no HSI motion enters the channel and no channel torque is
rendered (the HSI moves freely), and the TO's velocity reference is zero (under computed
torque the TO stops and holds its pose) while it feeds the channel no torque. The TO learns
the HSI's input with the channel's delay (its script is shifted by D ticks, as a packet would
bring it). On release r ramps back to 1, by at most ``dt / mapping.engage_ramp_s`` per tick
and by at most ``mapping.engage_step_nm / max|effort|`` (effort: the torque r multiplies,
tau_c at the HSI, beta tau_e at the TO), so the gain changes the rendered torque by at most
that much per tick. Energy: r enters as a transformer, so any r(t) is lossless and the
uncoupled interval's motion never reaches the channel (its integral of omega_c, the position
the wave integral and TDPA's drift compensation carry, does not advance): nothing is replayed.
The HSI's motion the channel did not carry, ``index_offset = integral of (1 - r) v_h dt``, is
the indexing offset: the TO tracks ``alpha (q_h - index_offset)``, which is what the summary's
T_p compares (and T_tau compares tau_h with ``beta tau_e``). The operator away for longer than
``mapping.presence_timeout_s`` is a safety stop (the staged stop of ``teleop_rt.site``).

Live inputs: with ``can.hsi.clutch_input`` / ``presence_input`` (a drive's 0x60FD bit) the
HSI's map also reads the backend's ``Feedback.inputs`` each tick, with the same ramp and
timeout. Its coupling state goes to the TO in every packet (``Packet.engaged``), and the TO's
map (``follow``) decouples on it, as on its script: r = 0, so its port is terminated (a matched
damper absorbs what is left of the waves in the channel: none of it is replayed on release)
and the same ramp on re-engaging. The TO reads the state of the packet of the tick before
(its port input goes out before this tick's packet arrives): it decouples D + 1 ticks after
the HSI, where the script shifted by D (kept for a scripted operator: the reference figures
bit for bit) does it after D. ``mapping.keys`` gives the HSI both inputs from the terminal's
keys instead (``teleop_rt.keys``); the map notes what it read (``inputs``), which the log
records with the gain, so that a replay feeds it back.

Frames (``mapping.offset_m``, ``mapping.rotation_rpy_deg``; task space only). The TO's tool is
to be at ``x_t = R (alpha x_h) + offset``, R a rotation (orthogonal, det 1). The channel's
port variables stay in the HSI's frame, so the whole frame map is the TO's:

    TO:   v_ref = r alpha J# (R omega_t)      tau_t = r beta R^T F_e      (F_e = J#^T tau_e)
          the position T_p compares: R^T (x_t - offset) + index_offset   (the HSI's frame)

R on velocities, R^T on forces: ``omega_t . (R^T F) = (R omega_t) . F``, so the power through
the map is the one without it, tick for tick, and everything above (the lever, Colgate's
power scale, Niemeyer and Slotine's wave impedance ``b / (alpha beta)``) holds as it is; the
map stays passive for any R because R^T R = I. R on the force instead of R^T would make power
(by the skew part of R^2) and is what the test's power identity catches. The offset moves no
robot: the channel carries motion, not positions, and T_p takes the motion since the first
tick; it places the positions logged (``q_mapped``) in one frame, so the two agree, within
the tracking error, when it is the offset between the robots' starting poses. An offset the
start does not meet therefore moves no robot (no jump): the TO starts where it stands.

In 3-D R is the full 3 x 3 rotation and the offset x, y, z. In the pose the twist's linear
and angular halves are each turned by R and the wrench's force and torque each by R^T
(the block-diagonal diag(R, R), again orthogonal: the same power identity), so the angular
velocity the TO's orientation reference integrates is R omega: R_t = R R_h C, C the constant
rotation between the tools at the start; the orientation T_p compares at the TO is
R^T log(R_t R_t0^T), which is log(R_h R_h0^T) when it follows. The offset has no angular part.

With the identity (alpha = beta = 1, no script) the block is inactive and the sites compute
exactly what they computed before it existed.
"""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.com.port import HSI, TO
from teleop_rt.config import SessionConfig
from teleop_rt.declarations import TASK_DIMS
from teleop_rt.flat import Block, Index, Int, Scalar, Vector, jit, vec
from teleop_rt.hal.signals import INPUT_CLUTCH, INPUT_PRESENT
from teleop_rt.task_math import dls_inverse, so3_exp, so3_log, times, times_transposed

PRESENCE_LOST = 200  # a site finding (teleop_rt.safety's codes are below 200)
# channel.space: joint to joint, or the tools in task space: x-y velocity and force (PLANE),
# x-y-z (POSITION), or the twist and wrench, world axes at the tool (POSE)
JOINT, PLANE, POSITION, POSE = 0, 1, 2, 3
SPACES = {"joint": JOINT, "plane": PLANE, "position": POSITION, "pose": POSE}
TASK = TASK_DIMS["plane"]  # the plane's dimension: the port's vectors hold x, y
POSE_DIM = TASK_DIMS["pose"]
# damped least squares (Wampler 1986; Nakamura & Hanafusa 1986): J# = J^T (J J^T + l^2 I)^-1,
# l in m (the SCARA's links are ~0.2 m: it acts within ~1 mm of a singular pose; in the pose
# the same l, in rad, for the angular rows, whose singular values are ~1)
DLS_DAMPING_M = 1e-3
# the DLS "acts" while J's smallest singular value is below 10 l: there the damping takes
# more than 1 % of the motion along the weakest direction (sigma^2 / (sigma^2 + l^2) < 0.99)
DLS_ACTIVE_SINGULAR = 10.0 * DLS_DAMPING_M
ROTATIONS = 5  # POSE: R, R0 (at the start), R_ref (the TO's reference), 2 scratch: 9 each
WALL_FLOATS = 6  # a virtual wall in the tail: x, y, unit normal x, y, stiffness, damping


@jit
def frame_dim(m: int) -> int:
    """The frames' dimension d for a task of m: the plane's 2, else 3 (position: x, y, z; the
    pose: its twist's linear and angular halves, each turned by the same 3 x 3 R)."""
    return m if m < 3 else 3


class Mapping(Block):
    """One site's map between its robot and its port (see the module's docstring)."""

    x = Vector("the port's input: r v_h (HSI), r beta tau_e (TO)")
    q_mapped = Vector(
        "indexed position: alpha (q_h - index_offset) (HSI), q_t + index_offset (TO), rad"
    )
    tau_mapped = Vector("TO: beta tau_e, the torque the HSI is to display, N m")
    index_offset = Vector("the motion the channel did not carry (HSI) or the TO did not follow")
    motion_scale = Scalar("alpha", param=True)
    force_scale = Scalar("beta", param=True)
    ramp_step = Scalar("the gain's largest rise per tick", param=True)
    step_limit = Scalar("N m: the gain's largest change of the torque it multiplies", param=True)
    dt = Scalar(param=True)
    gain = Scalar("r: 1 coupled, 0 decoupled")
    active = Int("0: the identity (the sites skip the map)", param=True)
    side = Int("HSI or TO", param=True)
    clutch_count = Int("clutch intervals in the tail", param=True)
    absent_count = Int("absence intervals in the tail", param=True)
    timeout_ticks = Int("away longer than this: a finding (-1: never)", param=True)
    clutch_at = Int("the first clutch interval not yet over")
    absent_at = Int("the first absence interval not yet over")
    live = Int("the live inputs read (INPUT_CLUTCH | INPUT_PRESENT bits; 0: script only)",
               param=True)
    live_away = Int("ticks the live presence input has been off, in a row")
    inputs = Int("the live inputs this tick's map read (of those ``live`` names; logged)")
    follow = Int("TO: 1: decoupled while the HSI's packets say so (it has live inputs)",
                 param=True)
    peer_engaged = Int("TO: the HSI's coupling state as of its newest packet (1: none yet)")
    coupled = Int("1: clutch released and operator present")
    engagements = Int("re-engagements so far")
    space = Int("JOINT, PLANE, POSITION or POSE", param=True)
    kin_at = Int("task space: where J (m x joints), J# (joints x m), the tool's m coordinates",
                 param=True)
    joints = Int("the robot's joints (the block's vectors: the port's size)", param=True)
    # the TO's task-space limits (safety.tool, teleop_rt.task_limits; PLANE only)
    limits = Int("1: the TO's tool limits are checked", param=True)
    walls = Int("virtual walls in the tail, after the kinematics", param=True)
    speed_limit = Scalar("m/s: the tool's speed limit (inf: none)", param=True)
    force_limit = Scalar("N: the tool's force limit, a stop (inf: none)", param=True)
    speed_cap = Scalar("the coupling gain's ceiling the speed limit sets for the next tick")
    min_speed_cap = Scalar("the lowest ceiling so far (1: the limit never acted)")
    peak_tool_speed = Scalar("m/s: the highest |J v| so far")
    peak_tool_force = Scalar("N: the highest measured |J#^T tau_e| so far")
    max_penetration = Scalar("m: the deepest the tool went beyond a virtual wall")
    max_wall_force = Scalar("N: the largest virtual wall force")
    speed_limited = Int("ticks the speed limit capped the gain")
    wall_ticks = Int("ticks a virtual wall pushed")
    # task space (PLANE, POSITION, POSE): the DLS's report, and the pose's orientation
    task = Int("the task's dimension (the port's size; 0: joint space)", param=True)
    work_at = Int("POSITION, POSE: the DLS's Cholesky factor, then its singular vector",
                  param=True)
    rot_at = Int("POSE: the tool's rotations R, R0, R_ref and 2 scratch, 9 floats each",
                 param=True)
    orientation_gain = Scalar("POSE, TO: K, 1/s: the angular velocity K log(R_ref R^T)",
                              param=True)
    dls_ticks = Int("ticks whose J# the DLS took more than 1 % of (sigma_min < 10 l)")
    min_singular = Scalar("the smallest singular value of J so far (inf: none yet)")
    # the frames (task space): x_t = R (alpha x_h) + offset, the TO's map only
    framed = Int("1: the TO's frame is rotated or offset against the HSI's", param=True)
    frame_at = Int(
        "where R (d x d, row major; d: frame_dim), the offset (d) and a task-sized scratch "
        "start", param=True,
    )
    # the posture task (task space, a redundant TO: ``to_posture``)
    posture_gain = Scalar("TO: k_p, 1/s, the null-space pull toward the posture (0: none)",
                          param=True)
    peak_posture_leak = Scalar("the largest |J (I - J# J) z| so far: the task motion the "
                               "posture term made (m/s; the pose: its largest entry)")
    posture_at = Int("where the posture (joints) and two task-sized scratches start", param=True)
    posture_held = Int("1: the posture is set (0: the first tick's q becomes it)")
    # the script: starts then ends of the clutch, then of the absences; then (task space) the
    # kinematics, refreshed by ``map_kinematics`` after every tick, the virtual walls, the
    # DLS's work (m > 2), the pose's rotations, the frame map and the posture
    TAIL_IS_STATE = False

    def __init__(
        self, n: int, side: int, dt: float, motion_scale: float = 1.0, force_scale: float = 1.0,
        clutch: list[tuple[int, int]] | None = None, absent: list[tuple[int, int]] | None = None,
        ramp_s: float = 0.0, step_limit: float = math.inf, timeout_ticks: int = -1,
        space: int = JOINT, joints: int | None = None, speed_limit: float = math.inf,
        force_limit: float = math.inf, walls: list[tuple[float, ...]] | None = None,
        live: int = 0, follow: bool = False, orientation_gain: float = 0.0,
        frame: tuple[np.ndarray, np.ndarray] | None = None, posture_gain: float = 0.0,
        posture: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """``n``: the port's size (the joints, or the task's dimension); ``joints``: the robot's
        (default n). ``speed_limit``, ``force_limit``, ``walls`` (x, y, nx, ny, k, d each):
        the TO's tool limits in the plane (``teleop_rt.task_limits``). ``live``: the
        backend's inputs (``Feedback.inputs``) read besides the script, INPUT_* bits;
        ``follow``: the TO decouples while the HSI's packets say it is decoupled.
        ``orientation_gain``: POSE at the TO, K of its orientation's correction (1/s). ``frame``:
        the TO's (R, offset), R d x d and the offset d (``frame_dim``; None: the frames
        agree). ``posture_gain``: at a redundant TO in task space (more joints than the task's
        dimension), k_p of its posture task (``to_posture``; 0: none, and elsewhere ignored);
        ``posture``: its joint angles (None: the configuration at the first tick)."""
        clutch, absent, walls = clutch or [], absent or [], walls or []
        script = 2 * (len(clutch) + len(absent))
        nj = n if joints is None else joints
        m = n if space != JOINT else 0  # J (m x nj), J# (nj x m), the tool's m coordinates
        kin = 2 * m * nj + m + WALL_FLOATS * len(walls) if space != JOINT else 0
        work = m * m + m if m > TASK else 0  # the DLS's Cholesky factor and singular vector
        rotations = 9 * ROTATIONS if space == POSE else 0
        if frame is not None and space == JOINT:
            raise ValueError("a frame map needs a task space")
        d = frame_dim(m)  # (R: d x d, the offset d, then an m-float scratch)
        framing = d * d + d + m if frame is not None else 0
        redundant = side == TO and space != JOINT and nj > m and posture_gain > 0.0
        posing = nj + 2 * m if redundant else 0  # the posture, then J z and J P z (m each)
        super().__init__(n, tail=script + kin + work + rotations + framing + posing)
        if redundant:  # (the tail's last)
            self.posture_gain = posture_gain
            self.posture_at = self.tail_start + self.tail - posing
            if posture is not None:
                self.f[self.posture_at : self.posture_at + nj] = posture
                self.posture_held = 1
        self.task = m
        self.work_at = self.tail_start + script + kin
        self.rot_at = self.work_at + work
        self.f[self.work_at + m * m : self.work_at + work] = 1.0 / math.sqrt(max(m, 1))
        self.orientation_gain = orientation_gain if space == POSE and side == TO else 0.0
        self.min_singular = math.inf
        self.speed_limit, self.force_limit, self.walls = speed_limit, force_limit, len(walls)
        self.limits = int(space == PLANE and (
            math.isfinite(speed_limit) or math.isfinite(force_limit) or bool(walls)))  # fmt: skip
        self.speed_cap = self.min_speed_cap = 1.0
        wall_at = self.tail_start + script + 2 * m * nj + m
        for k, wall in enumerate(walls):
            x, y, nx, ny, stiffness, damping = wall
            norm = math.hypot(nx, ny)  # (a unit normal: the penetration in m)
            at = wall_at + WALL_FLOATS * k
            self.f[at : at + WALL_FLOATS] = [x, y, nx / norm, ny / norm, stiffness, damping]
        self.space, self.joints = space, nj
        if frame is not None:
            rotation, offset = frame
            self.framed, self.frame_at = 1, self.rot_at + rotations  # (the tail's last)
            at = self.frame_at
            self.f[at : at + d * d] = np.asarray(rotation, dtype=float).reshape(-1)
            self.f[at + d * d : at + d * d + d] = offset
        self.kin_at = self.tail_start + script
        self.side, self.dt = side, dt
        self.motion_scale, self.force_scale = motion_scale, force_scale
        self.ramp_step = min(1.0, dt / ramp_s) if ramp_s > 0 else 1.0
        self.step_limit = step_limit
        self.timeout_ticks = timeout_ticks
        self.clutch_count, self.absent_count = len(clutch), len(absent)
        tail = self.f[self.tail_start :]
        for k, intervals in enumerate((clutch, absent)):
            at = 2 * len(clutch) * k
            tail[at : at + len(intervals)] = [a for a, _ in intervals]
            tail[at + len(intervals) : at + 2 * len(intervals)] = [b for _, b in intervals]
        self.live, self.follow, self.peer_engaged = live, int(follow), 1
        self.active = int(
            motion_scale != 1.0 or force_scale != 1.0 or bool(clutch or absent) or space != JOINT
            or live != 0 or follow
        )  # fmt: skip
        self.gain, self.coupled = 1.0, 1

    def take_live(self, live: int, follow: bool) -> None:
        """Read ``live`` inputs (the HSI) or follow the HSI's packets (the TO) as a logged run's
        site did, whatever this config's backend delivers (a replay: the logged ones)."""
        self.live, self.follow = live, int(follow)
        self.active = int(self.active or live != 0 or follow)




@jit
def _inside(f: np.ndarray, i: np.ndarray, at: int, count: int, cursor: int, tick: int) -> int:
    """Ticks since the interval containing ``tick`` began, + 1 (0: in none); intervals
    [start, end) at f[at:] (starts) and f[at + count:] (ends), walked forward by the cursor
    at i[cursor] (ticks only increase)."""
    k = i[cursor]
    while k < count and tick >= f[at + count + k]:
        k += 1
    i[cursor] = k
    if k < count and tick >= f[at + k]:
        return tick - int(f[at + k]) + 1
    return 0


@jit
def mapping_engage(
    f: np.ndarray, i: np.ndarray, n: int, tick: int, effort: np.ndarray, inputs: int
) -> int:  # fmt: skip
    """This tick's coupling gain r from the script and the live ``inputs`` (the feedback's,
    those ``live`` names); PRESENCE_LOST when the operator has been away too long (at the
    HSI), else 0. ``effort``: the torque r multiplies (its ramp's limit)."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    tail = s + Mi.N_SCALARS
    clutches, absences = i[Mi.CLUTCH_COUNT], i[Mi.ABSENT_COUNT]
    clutched = _inside(f, i, tail, clutches, Mi.CLUTCH_AT, tick) > 0
    away = _inside(f, i, tail + 2 * clutches, absences, Mi.ABSENT_AT, tick)
    live = i[Mi.LIVE]
    i[Mi.INPUTS] = inputs & live
    if live & INPUT_CLUTCH and inputs & INPUT_CLUTCH:
        clutched = True
    if i[Mi.FOLLOW] and not i[Mi.PEER_ENGAGED]:  # the HSI decoupled, as its packet said
        clutched = True
    if live & INPUT_PRESENT and not inputs & INPUT_PRESENT:
        i[Mi.LIVE_AWAY] += 1  # (counted like the script's: 1 on the first tick away)
    else:
        i[Mi.LIVE_AWAY] = 0
    away = max(away, i[Mi.LIVE_AWAY])
    if i[Mi.SIDE] == HSI and i[Mi.TIMEOUT_TICKS] >= 0 and away > i[Mi.TIMEOUT_TICKS]:
        return PRESENCE_LOST
    coupled = not clutched and away == 0
    r = f[s + Mi.GAIN]
    if not coupled:
        r = 0.0
    elif r < 1.0:
        step, peak = f[s + Mi.RAMP_STEP], 0.0
        for j in range(n):
            peak = max(peak, abs(effort[j]))
        if peak * step > f[s + Mi.STEP_LIMIT]:
            step = f[s + Mi.STEP_LIMIT] / peak
        r = min(1.0, r + step)
    if coupled and not i[Mi.COUPLED]:
        i[Mi.ENGAGEMENTS] += 1
    i[Mi.COUPLED] = 1 if coupled else 0
    f[s + Mi.GAIN] = r
    return 0


@jit
def hsi_map_input(f: np.ndarray, n: int, q: np.ndarray, v: np.ndarray) -> None:
    """The HSI's port input r v_h into x; the indexing offset and the mapped position."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    r, alpha, dt = f[s + Mi.GAIN], f[s + Mi.MOTION_SCALE], f[s + Mi.DT]
    x, q_mapped, offset = vec(f, Mi.X, n), vec(f, Mi.Q_MAPPED, n), vec(f, Mi.INDEX_OFFSET, n)
    for j in range(n):
        x[j] = r * v[j]
        offset[j] += (1.0 - r) * v[j] * dt
        q_mapped[j] = alpha * (q[j] - offset[j])


@jit
def to_map_input(f: np.ndarray, n: int, tau_e: np.ndarray) -> None:
    """beta tau_e into tau_mapped (before the gain: its ramp limits by it); r of it into x."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    beta = f[s + Mi.FORCE_SCALE]
    tau_mapped = vec(f, Mi.TAU_MAPPED, n)
    for j in range(n):
        tau_mapped[j] = beta * tau_e[j]


@jit
def to_map_output(f: np.ndarray, n: int, q: np.ndarray, omega_t: np.ndarray) -> None:
    """The TO's indexing offset (the channel's motion it did not follow while r < 1) and its
    indexed position q_t + offset."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    r, alpha, dt = f[s + Mi.GAIN], f[s + Mi.MOTION_SCALE], f[s + Mi.DT]
    q_mapped, offset = vec(f, Mi.Q_MAPPED, n), vec(f, Mi.INDEX_OFFSET, n)
    for j in range(n):
        offset[j] += (1.0 - r) * alpha * omega_t[j] * dt
        q_mapped[j] = q[j] + offset[j]


@jit
def to_map_gain(f: np.ndarray, n: int) -> None:
    """x = r beta tau_e, after ``mapping_engage`` set r."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    r = f[s + Mi.GAIN]
    x, tau_mapped = vec(f, Mi.X, n), vec(f, Mi.TAU_MAPPED, n)
    for j in range(n):
        x[j] = r * tau_mapped[j]


@jit
def map_kinematics(f: np.ndarray, i: np.ndarray, jac: np.ndarray, x: np.ndarray) -> None:
    """Task space: the tool's Jacobian rows 0 to m - 1 (of ``jac``, 6 x n, world-aligned:
    x, y in the plane, x, y, z for the position, and the angular rows after them in the
    pose), their damped least-squares inverse J# = J^T (J J^T + l^2 I)^-1 and the tool's
    position (of ``x``), for the next tick's map; the DLS's report. The same J# maps flow in
    and effort out, so the map stays lossless whatever l does to accuracy."""
    Mi = Mapping.idx
    k, n, m = i[Mi.KIN_AT], i[Mi.JOINTS], i[Mi.TASK]
    jj, inv, pos = k, k + m * n, k + 2 * m * n
    jj_, m_, n_ = Index(jj), Index(m), Index(n)  # (unsigned: flat.Index)
    for a in range(m_):
        for j in range(n_):
            f[jj_ + a * n_ + j] = jac[a, j]
    for a in range(min(m, 3)):
        f[pos + a] = x[a]
    damping = DLS_DAMPING_M * DLS_DAMPING_M
    if m > TASK:  # (Cholesky: teleop_rt.task_math)
        sigma2 = dls_inverse(f, jac, n, m, damping, inv, i[Mi.WORK_AT])
    else:  # the plane: A = J J^T + l^2 I (2 x 2), then J# = J^T A^-1
        a00 = a01 = a11 = 0.0
        for j in range(n):
            a00 += jac[0, j] * jac[0, j]
            a01 += jac[0, j] * jac[1, j]
            a11 += jac[1, j] * jac[1, j]
        half = 0.5 * (a00 - a11)  # sigma_min^2: J J^T's smaller eigenvalue
        sigma2 = 0.5 * (a00 + a11) - math.sqrt(half * half + a01 * a01)
        a00 += damping
        a11 += damping
        det = a00 * a11 - a01 * a01
        b00, b01, b11 = a11 / det, -a01 / det, a00 / det
        for j in range(n):
            f[inv + j * TASK] = jac[0, j] * b00 + jac[1, j] * b01
            f[inv + j * TASK + 1] = jac[0, j] * b01 + jac[1, j] * b11
    s = Mi.N_VECTORS * m
    sigma = math.sqrt(max(sigma2, 0.0))
    f[s + Mi.MIN_SINGULAR] = min(f[s + Mi.MIN_SINGULAR], sigma)
    if sigma < DLS_ACTIVE_SINGULAR:
        i[Mi.DLS_TICKS] += 1


@jit
def map_orientation(f: np.ndarray, i: np.ndarray, rot: np.ndarray) -> None:
    """POSE, after ``map_kinematics``: the tool's rotation R (``rot``, world), and the
    orientation's coordinates for T_p, log(R R0^T) (rad, world axes: the rotation since the
    start; their difference between the sites is the orientation error to first order, and
    exact for rotations about one axis)."""
    Mi = Mapping.idx
    at, pos = i[Mi.ROT_AT], i[Mi.KIN_AT] + 2 * POSE_DIM * i[Mi.JOINTS]
    for a in range(3):
        for b in range(3):
            f[at + 3 * a + b] = rot[a, b]
    times_transposed(f, at, at + 9, at + 27)
    so3_log(f, at + 27, pos + 3)


@jit
def map_tool(
    f: np.ndarray, i: np.ndarray, x: np.ndarray, rot: np.ndarray, jac: np.ndarray
) -> None:  # fmt: skip
    """Task space, after each tick's torques: ``map_kinematics`` and, in the pose,
    ``map_orientation`` (``rot``: the tool's rotation), in one compiled call (each call from
    Python costs a few hundred ns). ``jac`` last: the one argument that is new every tick
    (Pinocchio's Jacobian call returns a new array), so the site binds the others once
    (``flat.compiled_for``)."""
    Mi = Mapping.idx
    map_kinematics(f, i, jac, x)
    if i[Mi.SPACE] == POSE:
        map_orientation(f, i, rot)


@jit
def start_orientation(f: np.ndarray, i: np.ndarray) -> None:
    """POSE, at the start pose (after ``map_orientation``): R0 = R_ref = R, the coordinates 0."""
    Mi = Mapping.idx
    at, pos = i[Mi.ROT_AT], i[Mi.KIN_AT] + 2 * POSE_DIM * i[Mi.JOINTS]
    for a in range(9):
        f[at + 9 + a] = f[at + 18 + a] = f[at + a]
    for a in range(3):
        f[pos + 3 + a] = 0.0


@jit
def to_orientation_step(
    f: np.ndarray, i: np.ndarray, g_dt: float, omega_t: np.ndarray, error: np.ndarray
) -> None:  # fmt: skip
    """POSE at the TO, after C2's error took J# of the channel's twist: the orientation's
    correction J# (0, K e) added to it, e = log(R_ref R^T) the rotation (world axes) from the
    tool's orientation to its reference; then R_ref <- exp(g dt omega) R_ref, the rotation the
    channel commands this tick (g = r alpha), integrated on SO(3) for the next tick.

    Why the TO keeps a reference on SO(3): the channel's integral of its angular flow is no
    orientation (rotations do not commute), so unlike the position, which the wave integral
    and TDPA's drift compensation carry, the orientation the TO lost to the DLS, its velocity
    loop's lag or the one-tick stale J would never be taken up. With omega = K e about a fixed
    axis, d/dt (R_ref R^T) = -(R_ref R^T) [omega]x gives de/dt = -K e: a first-order approach at
    the rate K (Siciliano's closed-loop inverse kinematics, Robotica 1990, on SO(3)). Decoupled
    (g = 0), R_ref stands still and the TO holds its orientation."""
    Mi = Mapping.idx
    at, nj = i[Mi.ROT_AT], i[Mi.JOINTS]
    inv = i[Mi.KIN_AT] + POSE_DIM * nj
    gain = f[Mi.N_VECTORS * POSE_DIM + Mi.ORIENTATION_GAIN]
    if gain > 0.0:
        e = at + 36  # (the second scratch: its first 3 floats)
        times_transposed(f, at + 18, at, at + 27)
        so3_log(f, at + 27, e)
        for j in range(nj):
            row = inv + j * POSE_DIM + 3
            error[j] += gain * (f[row] * f[e] + f[row + 1] * f[e + 1] + f[row + 2] * f[e + 2])
    so3_exp(f, g_dt * omega_t[3], g_dt * omega_t[4], g_dt * omega_t[5], at + 27)
    times(f, at + 27, at + 18, at + 36)
    for a in range(9):
        f[at + 18 + a] = f[at + 36 + a]


@jit
def hsi_plane_input(
    f: np.ndarray, i: np.ndarray, n: int, v: np.ndarray, tau_h: np.ndarray
) -> None:  # fmt: skip
    """Task space at the HSI: omega_c = r J v_h; the indexing offset and the indexed tool
    position alpha (x_h - offset); the operator's force J#^T tau_h (for T_tau). ``n``: the
    port's size, the task's dimension; the robot's joints are the block's ``joints``."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    k, nj, m = Index(i[Mi.KIN_AT]), Index(i[Mi.JOINTS]), Index(n)  # (unsigned: flat.Index)
    jj, inv, pos = k, k + m * nj, k + Index(2) * m * nj
    r, alpha, dt = f[s + Mi.GAIN], f[s + Mi.MOTION_SCALE], f[s + Mi.DT]
    x, q_mapped, offset = vec(f, Mi.X, n), vec(f, Mi.Q_MAPPED, n), vec(f, Mi.INDEX_OFFSET, n)
    force = vec(f, Mi.TAU_MAPPED, n)
    for a in range(m):
        xd = 0.0
        fa = 0.0
        for j in range(nj):
            xd += f[jj + a * nj + j] * v[j]
            fa += f[inv + j * m + a] * tau_h[j]
        x[a] = r * xd
        offset[a] += (1.0 - r) * xd * dt
        q_mapped[a] = alpha * (f[pos + a] - offset[a])
        force[a] = fa


@jit
def hsi_plane_render(
    f: np.ndarray, i: np.ndarray, n: int, tau_h: np.ndarray, tau_c: np.ndarray,
    error: np.ndarray,
) -> None:  # fmt: skip
    """Task space at the HSI: C1's error tau_h - r J^T F_c."""
    Mi = Mapping.idx
    s, jj, nj = Mi.N_VECTORS * n, Index(i[Mi.KIN_AT]), Index(i[Mi.JOINTS])
    r = f[s + Mi.GAIN]
    for j in range(nj):
        rendered = 0.0
        for a in range(Index(n)):
            rendered += f[jj + a * nj + j] * tau_c[a]
        error[j] = tau_h[j] - r * rendered


@jit
def to_plane_input(f: np.ndarray, i: np.ndarray, n: int, tau_e: np.ndarray) -> None:
    """Task space at the TO: the environment's force beta J#^T tau_e into tau_mapped."""
    Mi = Mapping.idx
    nj, m = Index(i[Mi.JOINTS]), Index(n)
    s, inv = Mi.N_VECTORS * n, Index(i[Mi.KIN_AT]) + m * nj
    beta = f[s + Mi.FORCE_SCALE]
    force = vec(f, Mi.TAU_MAPPED, n)
    for a in range(m):
        fa = 0.0
        for j in range(nj):
            fa += f[inv + j * m + a] * tau_e[j]
        force[a] = beta * fa


@jit
def to_plane_output(
    f: np.ndarray, i: np.ndarray, n: int, omega_t: np.ndarray, v: np.ndarray,
    error: np.ndarray,
) -> None:  # fmt: skip
    """Task space at the TO: C2's error r alpha J# omega_t - v_t (in the pose, with the
    orientation's correction: ``to_orientation_step``); the indexing offset and the indexed
    tool position x_t + offset. Framed: the flow turned into the TO's frame first (R omega_t,
    each 3-vector of a twist by R), and the position T_p compares R^T (x_t - offset) (the
    pose's orientation coordinates R^T log(R_t R_t0^T)) + index offset, the HSI's frame."""
    Mi = Mapping.idx
    s, k, nj = Mi.N_VECTORS * n, i[Mi.KIN_AT], i[Mi.JOINTS]
    inv, pos = k + n * nj, k + 2 * n * nj
    r, alpha, dt = f[s + Mi.GAIN], f[s + Mi.MOTION_SCALE], f[s + Mi.DT]
    g = r * alpha
    q_mapped, offset = vec(f, Mi.Q_MAPPED, n), vec(f, Mi.INDEX_OFFSET, n)
    framed, fr, d = i[Mi.FRAMED] != 0, i[Mi.FRAME_AT], frame_dim(n)
    w = fr + d * d + d
    flow = omega_t
    if framed:  # the flow in the TO's frame, R omega_t, into the scratch
        frame_turn(f, fr, d, n, omega_t, w, False)
        flow = f[w : w + n]
    inv_, m = Index(inv), Index(n)  # (unsigned: flat.Index)
    for j in range(Index(nj)):
        v_ref = 0.0
        for a in range(m):
            v_ref += f[inv_ + j * m + a] * flow[a]
        error[j] = g * v_ref - v[j]
    if i[Mi.SPACE] == POSE:
        to_orientation_step(f, i, g * dt, flow, error)
    for a in range(n):
        offset[a] += (1.0 - r) * alpha * omega_t[a] * dt
    if framed:  # R^T (x_t - offset), in the HSI's frame (the scratch's flow is used up)
        for a in range(n):
            f[w + a] = f[pos + a] - (f[fr + d * d + a] if a < d else 0.0)
        frame_turn(f, fr, d, n, f[w : w + n], w, True)
        for a in range(n):
            q_mapped[a] = f[w + a] + offset[a]
    else:
        for a in range(n):
            q_mapped[a] = f[pos + a] + offset[a]


@jit
def to_posture(f: np.ndarray, i: np.ndarray, n: int, q: np.ndarray, error: np.ndarray) -> None:
    """Task space at a redundant TO (nj joints > the task's n), after ``to_plane_output``: the
    posture task's joint velocity (I - J# J) z, z = k_p (q_posture - q), added to C2's error.

    The gradient projection of Liegeois ("Automatic supervisory control of the configuration
    and behavior of multibody mechanisms", IEEE T-SMC 1977) with the cost k_p |q - q_p|^2 / 2,
    i.e. the second task of Nakamura, Hanafusa & Yoshikawa's task priority ("Task-priority
    based redundancy control of robot manipulators", IJRR 1987) when the second task is the
    whole configuration, its velocity z (their J2 = I: with the exact pseudo-inverse P is
    symmetric idempotent and P J^+ = 0, so their second term is P z); Siciliano & Slotine
    ("A general framework for managing multiple tasks in highly redundant robotic systems",
    ICAR 1991) give it as the lowest priority. Why a
    posture and not null-space damping -k_d P v: C2 already acts on v_ref - v, so the null
    space's velocity is already damped toward 0 (at the velocity loop's rate 1 / T2); what
    nothing restores is its position, which drifts (J# is one tick stale, damped, and the plane
    leaves z and the orientation free). With T2 = M2 / c2 the same on every joint, a posture
    offset in the null space obeys T2 e'' + e' + k_p e = 0: exp(-k_p t) for k_p T2 << 1.

    The projector is the DLS's own, P = I - J# J = I - J^T A^-1 J (A = J J^T + l^2 I, J# as
    ``map_kinematics`` wrote it): symmetric, eigenvalue 1 on J's null space (exact there) and
    l^2 / (sigma^2 + l^2) along each row-space direction of singular value sigma. So it is not
    quite a null-space projector: J P z = l^2 A^-1 J z (since J J# = I - l^2 A^-1), the leak,
    |J P z| <= l^2 / (sigma_min^2 + l^2) |J z|, at most l / 2 |z| whatever sigma (1e-5 of
    |J z| at sigma_min = 0.3 m). It is computed here, J (P z), at no extra storage, and its
    largest |entry| is reported (``peak_posture_leak``). Passivity: the channel's port
    variables (omega_t in, r beta J#^T tau_e out) do not contain the term, and the power it
    does on a force F at the tool (tau_e = J^T F) is F . J P z, the leak's, and what the
    one-tick stale J leaves, F . (J - J_stale) P z (tests/test_posture.py: 4e-6 of the
    port's peak power). Near a singularity the leak is the damping's own trade:
    the posture's motion then moves the tool along the weak direction, as J#'s task motion
    loses it."""
    Mp = Mapping.idx
    nj, k = i[Mp.JOINTS], i[Mp.KIN_AT]
    jj, inv = k, k + n * nj
    at = i[Mp.POSTURE_AT]
    w, leak = at + nj, at + nj + n
    s = Mp.N_VECTORS * n
    gain = f[s + Mp.POSTURE_GAIN]
    if not i[Mp.POSTURE_HELD]:  # the first tick's configuration
        for j in range(nj):
            f[at + j] = q[j]
        i[Mp.POSTURE_HELD] = 1
    for a in range(n):  # J z
        ja = 0.0
        for j in range(nj):
            ja += f[jj + a * nj + j] * (f[at + j] - q[j])
        f[w + a] = gain * ja
        f[leak + a] = 0.0
    for j in range(nj):  # P z = z - J# (J z), and the leak J (P z)
        pz = gain * (f[at + j] - q[j])
        for a in range(n):
            pz -= f[inv + j * n + a] * f[w + a]
        error[j] += pz
        for a in range(n):
            f[leak + a] += f[jj + a * nj + j] * pz
    peak = f[s + Mp.PEAK_POSTURE_LEAK]
    for a in range(n):
        peak = max(peak, abs(f[leak + a]))
    f[s + Mp.PEAK_POSTURE_LEAK] = peak


@jit
def frame_turn(
    f: np.ndarray, fr: int, d: int, n: int, x: np.ndarray, out: int, transposed: bool
) -> None:  # fmt: skip
    """f[out : out + n] = R x (R^T x if ``transposed``), R (d x d) at f[fr:] applied to each
    d-vector of x (the pose's twist or wrench: its linear, then its angular half). ``x`` may
    be the output's own floats: each d-vector is read whole before it is written."""
    for c in range(0, n, d):
        x0 = x[c]
        x1 = x[c + 1]
        x2 = x[c + 2] if d == 3 else 0.0
        for a in range(d):
            if transposed:  # (row a of R^T: column a of R)
                ya = f[fr + a] * x0 + f[fr + d + a] * x1
                if d == 3:
                    ya += f[fr + 2 * d + a] * x2
            else:
                ya = f[fr + a * d] * x0 + f[fr + a * d + 1] * x1
                if d == 3:
                    ya += f[fr + a * d + 2] * x2
            f[out + c + a] = ya


@jit
def to_frame_force(f: np.ndarray, i: np.ndarray, n: int) -> None:
    """Framed, at the TO, after its force is complete (``to_plane_input``, the virtual walls):
    tau_mapped = R^T (beta F_e), the force in the HSI's frame (the port's; the pose: both the
    wrench's force and its torque turned by R^T)."""
    Mi = Mapping.idx
    if not i[Mi.FRAMED]:
        return
    force = vec(f, Mi.TAU_MAPPED, n)
    frame_turn(f, i[Mi.FRAME_AT], frame_dim(n), n, force, Mi.TAU_MAPPED * n, True)


def mapping_for(cfg: SessionConfig, joints: int, side: int) -> Mapping:
    """Site ``side``'s map from the config (``mapping`` and the operator's script); the TO's
    script is the HSI's shifted by the channel's delay (when the HSI's input reaches it)."""
    spec, rate = cfg.mapping, cfg.rate_hz
    shift = cfg.delay_ticks if side == TO else 0

    def ticks(intervals: list) -> list[tuple[int, int]]:
        return [(round(w.start_s * rate) + shift, round(w.end_s * rate) + shift)
                for w in intervals]  # fmt: skip

    timeout = spec.presence_timeout_s
    space = SPACES[cfg.channel.space]
    tool = cfg.safety.tool
    limited = side == TO and cfg.safety.enabled  # (the guard's other limits follow it too)
    inf = math.inf
    speed = tool.speed_limit_m_s if limited and tool.speed_limit_m_s is not None else inf
    force = tool.force_limit_n if limited and tool.force_limit_n is not None else inf
    walls = [(*w.point_m, *w.normal, w.stiffness_n_per_m, w.damping_n_s_per_m)
             for w in (tool.walls if limited else [])]  # fmt: skip
    return Mapping(
        port_size(cfg.channel.space, joints), side, cfg.dt, spec.motion_scale, spec.force_scale,
        ticks(cfg.operator.clutch), ticks(cfg.operator.absent), spec.engage_ramp_s,
        spec.engage_step_nm, -1 if timeout is None else round(timeout * rate),
        space, joints, speed, force, walls, live_inputs(cfg) if side == HSI else 0,
        side == TO and live_inputs(cfg) != 0, spec.orientation_gain_per_s,
        frame_for(cfg) if side == TO and spec.framed else None, spec.posture_gain_per_s,
        None if spec.posture_rad is None else np.array(spec.posture_rad, dtype=float),
    )  # fmt: skip


def port_size(space: str, joints: int) -> int:
    """The port's vector length: the robot's joints, or the task's dimension."""
    return TASK_DIMS.get(space, joints)


def dls_figures(mapping: Mapping) -> dict | None:
    """What the damped least squares did at a task-space site, for the summary (None in joint
    space): the ticks it took more than 1 % of the weakest direction's motion, and the
    smallest singular value of J it met (sigma_min; DLS_DAMPING_M is l)."""
    if mapping.space == JOINT:
        return None
    low = float(mapping.min_singular)
    return {
        "active_ticks": int(mapping.dls_ticks),
        "min_singular_value": low if math.isfinite(low) else None,
        "active_below": DLS_ACTIVE_SINGULAR,
        "damping": DLS_DAMPING_M,
    }


def frame_rotation(rpy_deg: tuple[float, float, float]) -> np.ndarray:
    """The 3 x 3 rotation of roll, pitch, yaw (deg) about the fixed x, y, z axes,
    R = Rz(yaw) Ry(pitch) Rx(roll): URDF's rpy, as Pinocchio's ``rpy.rpyToMatrix`` takes it."""
    import pinocchio as pin

    return np.asarray(pin.rpy.rpyToMatrix(*np.radians(rpy_deg)), dtype=float)


def frame_for(cfg: SessionConfig) -> tuple[np.ndarray, np.ndarray]:
    """The TO's (R, offset) of the task space from ``mapping``: in the plane, R's x-y block
    (the config holds it to a yaw) and the offset's x, y; in 3-D and in the pose, all of
    both (``frame_dim``)."""
    spec = cfg.mapping
    d = frame_dim(TASK_DIMS[cfg.channel.space])
    return frame_rotation(spec.rotation_rpy_deg)[:d, :d], np.array(spec.offset_m[:d])


def live_inputs(cfg: SessionConfig) -> int:
    """The INPUT_* bits the HSI's feedback delivers: both with ``mapping.keys`` (the terminal's
    keys, ``teleop_rt.keys``), else the CAN backend's ``can.hsi`` ``clutch_input`` /
    ``presence_input`` (off unless given)."""
    if cfg.mapping.keys:
        return INPUT_CLUTCH | INPUT_PRESENT
    if cfg.backend_for("hsi") != "can" or cfg.can is None:
        return 0
    side = cfg.can.hsi
    return (INPUT_CLUTCH if side.clutch_input is not None else 0) | (
        INPUT_PRESENT if side.presence_input is not None else 0)  # fmt: skip
