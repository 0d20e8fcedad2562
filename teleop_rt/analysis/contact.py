"""Stability limit of the sampled contact loop at the TO, even without delay.

At the TO the channel closes a local loop through the environment: the TO side of eq 9 gives
``omega_t = (sqrt(2b) u_r - tau_t) / b``, so a contact stiffness K (joint space, N m/rad) feeds
back ``-K q / b`` into the velocity reference. With the P velocity controller (eq 14, T2 = M2/c2)
on the computed-torque plant, symplectic Euler at dt, and tau_t measured at the start of the
tick, the joint's state (q, v) obeys

    v[k+1] = (1 - a) v[k] - a (K / b) q[k],   q[k+1] = q[k] + dt v[k+1],   a = dt / T2,

whose characteristic polynomial is  z^2 - (2 - a - a g) z + (1 - a),  g = K dt / b.
Jury's conditions give  0 < a < 2  and  g < (4 - 2a) / a, that is

    K < K_max = b (4 T2 - 2 dt) / dt^2.

(Continuous time has no limit: T2 s^2 + s + K/b is stable for any K > 0.) A Cartesian wall of
stiffness k acts in joint space as J^T k n n^T J, whose largest eigenvalue must stay below
K_max with margin.
"""

from __future__ import annotations

import math

import numpy as np


def contact_stiffness_limit(b: float, m2: float, c2: float, dt: float) -> float:
    """K_max (N m/rad) of the sampled TO contact loop for a P velocity controller.

    c2 = 0 (a PID's pure I or D term) closes no proportional loop: K_max grows without bound as
    c2 falls (T2 = M2/c2), so there is no limit from this analysis."""
    if c2 == 0:
        return math.inf
    t2 = m2 / c2
    if dt / t2 >= 2.0:
        return 0.0  # the velocity loop alone is already unstable at this tick
    return b * (4.0 * t2 - 2.0 * dt) / dt**2


def joint_space_stiffness(jacobian: np.ndarray, k_n_per_m: float, normal: np.ndarray) -> float:
    """Largest eigenvalue of J^T (k n n^T) J: the stiffest joint-space direction of a wall."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    j = np.asarray(jacobian, dtype=float)[:3]
    stiffness = j.T @ (k_n_per_m * np.outer(n, n)) @ j
    return float(np.linalg.eigvalsh(stiffness).max())


WARN_FRACTION = 0.5  # walls are stiffer in some poses than at q0: warn with margin


def contact_warnings(cfg, to_model) -> list[str]:
    """One line per environment element stiffer (at the TO's start pose) than WARN_FRACTION of
    the sampled contact loop's limit. ``cfg``: SessionConfig; ``to_model``: the TO RobotModel."""
    from teleop_rt.config import per_joint

    if cfg.channel.space != "joint":
        # the bound is the joint-space loop's (b per joint, N m s/rad); in task space b is the
        # tool's (N s/m; a pose's per component, not per joint): no bound of this analysis
        return []
    n = to_model.nv
    q0 = np.array(per_joint(cfg.to.robot.q0_rad, n, "to.robot.q0_rad") or [0.0] * n)
    b = per_joint(cfg.channel.wave_impedance, n, "channel.wave_impedance")
    m2 = per_joint(cfg.to.virtual_mass, n, "to.virtual_mass")
    c2 = per_joint(cfg.to.controller.kp, n, "to.controller.kp")
    limits = [contact_stiffness_limit(b[j], m2[j], c2[j], cfg.dt) for j in range(n)]
    if 0.0 in limits:  # (no contact bound to divide by: say what is wrong instead)
        j = limits.index(0.0)
        return [
            f"to joint {j}: its velocity loop alone is unstable at rate_hz = {cfg.rate_hz} "
            f"(dt / T2 = {cfg.dt * c2[j] / m2[j]:.3g} >= 2, T2 = M2/c2; see "
            "teleop_rt/analysis/contact.py): raise rate_hz or T2"
        ]
    limit = min(limits)
    to_model.update_ee(q0, [0.0] * n)
    jacobian = np.array(to_model.ee_jac[:3]).reshape(3, n)
    out = []
    for i, env in enumerate(cfg.environment):
        k = getattr(env, "stiffness_n_per_m", 0.0) or getattr(env, "contact_stiffness_n_per_m", 0.0)
        if not k:
            continue
        normal = np.zeros(3)
        normal[: len(env.normal)] = env.normal
        k_joint = joint_space_stiffness(jacobian, k, normal)
        if k_joint > WARN_FRACTION * limit:
            # the fraction itself: "above 50 %" read as the share for a wall at 190 %
            beyond = k_joint > limit
            out.append(
                f"environment.{i} ({env.kind}, {k:g} N/m) is {k_joint:.0f} N m/rad in joint space "
                f"at the TO's start pose, {k_joint / limit:.0%} of the sampled contact loop's "
                f"limit {limit:.0f} N m/rad (b (4 T2 - 2 dt) / dt^2, see teleop_rt/analysis/"
                f"contact.py; warned above {WARN_FRACTION:.0%}): "
                + ("beyond it the contact is unstable" if beyond else "expect ringing")
                + "; lower the stiffness or raise b or T2 = M2/c2"
            )
    return out
