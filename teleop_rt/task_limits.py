"""The TO's limits in task space (issue 26; ``safety.tool``, ``channel.space: plane``): the
tool's speed, its force, and virtual walls, each acting so that the coupling stays passive.

* **Speed** (``speed_limit_m_s``): a ceiling on the TO's coupling gain r
  (``teleop_rt.mapping``), r <= v_max / (alpha |omega_t|), set from this tick's channel
  flow for the next tick (the TO's outgoing effort is formed before its flow arrives). r
  multiplies the velocity reference and the fed-back force alike, so the TO's map stays the
  lossless transformer it is for the clutch: the limit slips the coupling (the motion the TO
  does not follow goes to its indexing offset) and never makes energy. Falling, the ceiling
  acts at once; rising, r comes back through the engage ramp (``mapping.engage_ramp_s``,
  ``engage_step_nm``), so the limit's release is as jump-free as a re-engage. The reference
  speed is v_max |omega_t[k+1]| / |omega_t[k]|, v_max to within the flow's change in a tick.
* **Force** (``force_limit_n``): the TO's measured force at the tool, |J#^T tau_e|, above
  the limit is a safety stop (the staged stop of ``teleop_rt.site``), as the joint torque
  limit is with ``safety.torque_limits: stop``.
* **Virtual walls** (``walls``): beyond a wall (penetration p > 0 along its unit normal n) a
  unilateral spring-damper F_w = max(0, k p + d dp/dt) n pushes the tool back, rendered as
  part of the TO's environment: tau_e in task space becomes J#^T tau_e - F_w, which the
  channel feeds back, so the operator feels the workspace's edge as a wall. It is passive
  with the storage k p^2 / 2: the power it takes is F_w dp/dt = k p dp/dt + d (dp/dt)^2 when
  it pushes, and when the clamp holds it at 0 (k p + d dp/dt < 0, the tool leaving faster
  than the spring relaxes) it takes 0 while its storage falls. Sampled, a wall can return a
  little more than it took (Colgate & Schenkel, "Passivity of a class of sampled-data
  systems", J. Robotic Systems 1997: d > k dt / 2 bounds it); the channel's own energy (eq 7)
  stays >= 0 whatever the termination. A hard edge is the workspace box's stop
  (``safety.workspace.to``).

All of it runs in the TO's compiled site kernels, on the mapping block's Jacobian of the
previous tick (as the map itself does), and only when ``safety.tool`` sets something: a
joint-space run, or one without limits, computes exactly what it did before.
"""

from __future__ import annotations

import math

import numpy as np

from teleop_rt.flat import jit, vec
from teleop_rt.mapping import (
    TASK,
    WALL_FLOATS,
    Mapping,
)

TOOL_FORCE = 201  # a site finding (the mapping's are from 200)


@jit
def to_tool_sense(f: np.ndarray, i: np.ndarray, n: int, v: np.ndarray) -> int:
    """After ``to_plane_input`` (tau_mapped = beta J#^T tau_e): the force limit on the
    measured |J#^T tau_e| (TOOL_FORCE, else 0), then the virtual walls' forces,
    tau_mapped -= beta F_w."""
    Mi = Mapping.idx
    s, k, nj = Mi.N_VECTORS * n, i[Mi.KIN_AT], i[Mi.JOINTS]
    beta = f[s + Mi.FORCE_SCALE]
    force = vec(f, Mi.TAU_MAPPED, n)
    measured = math.hypot(force[0], force[1]) / beta
    f[s + Mi.PEAK_TOOL_FORCE] = max(f[s + Mi.PEAK_TOOL_FORCE], measured)
    if measured > f[s + Mi.FORCE_LIMIT]:
        return TOOL_FORCE
    walls = i[Mi.WALLS]
    if walls == 0:
        return 0
    jj, pos = k, k + 4 * nj
    x, y = f[pos], f[pos + 1]
    xd = yd = 0.0
    for j in range(nj):
        xd += f[jj + j] * v[j]
        yd += f[jj + nj + j] * v[j]
    pushed = False
    for w in range(walls):
        at = pos + TASK + WALL_FLOATS * w
        nx, ny = f[at + 2], f[at + 3]
        depth = -((x - f[at]) * nx + (y - f[at + 1]) * ny)
        if depth <= 0.0:
            continue
        push = f[at + 4] * depth - f[at + 5] * (xd * nx + yd * ny)  # k p + d dp/dt
        f[s + Mi.MAX_PENETRATION] = max(f[s + Mi.MAX_PENETRATION], depth)
        if push <= 0.0:
            continue
        pushed = True
        f[s + Mi.MAX_WALL_FORCE] = max(f[s + Mi.MAX_WALL_FORCE], push)
        force[0] -= beta * push * nx  # the TO pushes the wall with -F_w
        force[1] -= beta * push * ny
    if pushed:
        i[Mi.WALL_TICKS] += 1
    return 0


@jit
def to_speed_ceiling(f: np.ndarray, n: int) -> None:
    """After ``mapping_engage``: r = min(r, the speed limit's ceiling)."""
    Mi = Mapping.idx
    s = Mi.N_VECTORS * n
    f[s + Mi.GAIN] = min(f[s + Mi.GAIN], f[s + Mi.SPEED_CAP])


@jit
def to_speed_limit(
    f: np.ndarray, i: np.ndarray, n: int, omega_t: np.ndarray, v: np.ndarray
) -> None:  # fmt: skip
    """After the TO's flow omega_t arrived: the next tick's ceiling v_max / (alpha |omega_t|)
    (at most 1), and the tool's speed |J v| for the summary."""
    Mi = Mapping.idx
    s, k, nj = Mi.N_VECTORS * n, i[Mi.KIN_AT], i[Mi.JOINTS]
    wanted = f[s + Mi.MOTION_SCALE] * math.hypot(omega_t[0], omega_t[1])
    limit = f[s + Mi.SPEED_LIMIT]
    cap = 1.0 if wanted <= limit else limit / wanted
    f[s + Mi.SPEED_CAP] = cap
    if cap < 1.0:
        i[Mi.SPEED_LIMITED] += 1
        f[s + Mi.MIN_SPEED_CAP] = min(f[s + Mi.MIN_SPEED_CAP], cap)
    xd = yd = 0.0
    for j in range(nj):
        xd += f[k + j] * v[j]
        yd += f[k + nj + j] * v[j]
    f[s + Mi.PEAK_TOOL_SPEED] = max(f[s + Mi.PEAK_TOOL_SPEED], math.hypot(xd, yd))


def tool_limits_figures(mapping: Mapping) -> dict | None:
    """What the TO's tool limits did, for the summary (None: no limits configured)."""
    if not mapping.limits:
        return None
    return {
        "speed_limit_m_s": mapping.speed_limit if math.isfinite(mapping.speed_limit) else None,
        "speed_limited_ticks": int(mapping.speed_limited),
        "min_speed_gain": float(mapping.min_speed_cap),
        "peak_tool_speed_m_s": float(mapping.peak_tool_speed),
        "force_limit_n": mapping.force_limit if math.isfinite(mapping.force_limit) else None,
        "peak_tool_force_n": float(mapping.peak_tool_force),
        "walls": int(mapping.walls),
        "wall_ticks": int(mapping.wall_ticks),
        "max_penetration_m": float(mapping.max_penetration),
        "max_wall_force_n": float(mapping.max_wall_force),
    }
