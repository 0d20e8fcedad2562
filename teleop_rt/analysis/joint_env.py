"""A session config's environment as the joint-space Z_e of one joint, for ``teleop-rt bode``.

The environment acts at the TO's tool in Cartesian space (``teleop_rt.world``); the open chain
of ``teleop_rt.analysis.bode`` loads one joint with Z_e = m s + d + k/s. Linearised at the TO's
start pose q0, an element along the unit normal n contributes through the tool Jacobian's column
of that joint, J_j: a stiffness k (n . J_j)^2 N m/rad, a damping d (n . J_j)^2, an attached mass
m (n . J_j)^2 kg m^2. Walls and foam are unilateral: they count if the tool touches them at q0;
if it touches none, the nearest one is taken as touched (with the Jacobian at q0, and how far
away it is said): a config that has a wall is about the wall, and the displayed wall (eq 30) is
what its Bode plot should show, not the free space before it. A free mass behind a contact
spring is not of the form m s + d + k/s and is left out, said so. Every element gets one line
saying how it was used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class JointEnvironment:
    """Z_e = mass s + damping + stiffness / s of one joint, and where each part came from."""

    mass: float = 0.0  # kg m^2
    damping: float = 0.0  # N m s/rad
    stiffness: float = 0.0  # N m/rad
    elements: list[str] = field(default_factory=list)  # environment.i: how it was used

    @property
    def source(self) -> str:
        if not self.elements:
            return "free space (the config has no environment)"
        return "the config's environment at the TO's start pose: " + "; ".join(self.elements)


def joint_environment(cfg, joint: int, to_model=None) -> JointEnvironment:
    """The config's environment as the joint-space load of ``joint`` at the TO's q0.

    ``cfg``: SessionConfig; ``to_model``: its TO RobotModel (loaded if not given)."""
    from teleop_rt.config import per_joint
    from teleop_rt.model import RobotModel

    out = JointEnvironment()
    if not cfg.environment:
        return out
    model = to_model or RobotModel.from_spec(cfg.to.robot, "to")
    n = model.nv
    q0 = np.array(per_joint(cfg.to.robot.q0_rad, n, "to.robot.q0_rad") or [0.0] * n)
    model.update_ee(q0, [0.0] * n)
    tool = np.array(model.ee_pos, dtype=float)
    column = np.array(model.ee_jac, dtype=float)[:3, joint] if joint < n else np.zeros(3)
    away: list[tuple[float, int, int, float]] = []  # out of reach: gap, note, element, lever
    touched = False
    for i, env in enumerate(cfg.environment):
        normal = np.zeros(3)
        normal[: len(env.normal)] = env.normal
        normal /= np.linalg.norm(normal)
        point = np.zeros(3)
        point[: len(env.point_m)] = env.point_m
        lever2 = float(np.dot(normal, column)) ** 2  # (n . J_j)^2, m^2/rad^2
        gap = float(np.dot(tool - point, normal))  # > 0: the tool is on the free side
        name = f"environment.{i} ({env.kind})"
        if env.kind in ("wall", "foam") and gap > 0:
            away.append((gap, len(out.elements), i, lever2))
            out.elements.append(f"{name} not in contact at q0 ({gap * 1000:.1f} mm away): free")
            continue
        touched = touched or env.kind in ("wall", "foam")
        if env.kind == "mass" and not env.attached:
            out.elements.append(f"{name}: a free mass behind a contact spring, not used")
            continue
        if env.kind == "mass":
            out.mass += env.mass_kg * lever2
            what = f"{env.mass_kg * lever2:.4g} kg m^2"
        else:
            out.stiffness += env.stiffness_n_per_m * lever2
            out.damping += env.damping_n_s_per_m * lever2
            what = (
                f"{env.stiffness_n_per_m * lever2:.4g} N m/rad, "
                f"{env.damping_n_s_per_m * lever2:.4g} N m s/rad"
            )
        out.elements.append(f"{name}: {what} on joint {joint} (n . J_j = {np.sqrt(lever2):.3g} m)")
    if away and not touched:  # the nearest contact, as if touched
        gap, at, i, lever2 = min(away)
        env = cfg.environment[i]
        name = f"environment.{i} ({env.kind})"
        out.stiffness += env.stiffness_n_per_m * lever2
        out.damping += env.damping_n_s_per_m * lever2
        out.elements[at] = (
            f"{name} not in contact at q0 ({gap * 1000:.1f} mm away), the nearest contact: taken "
            f"as touched, {env.stiffness_n_per_m * lever2:.4g} N m/rad, "
            f"{env.damping_n_s_per_m * lever2:.4g} N m s/rad on joint {joint} "
            f"(n . J_j = {np.sqrt(lever2):.3g} m at q0)"
        )
    return out
