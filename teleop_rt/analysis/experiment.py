"""Figures of the paper's experiment (Sec 5, Fig 6) from a run's signals: the displayed mass
in free space, the penetration of both tools into the wall and the stiffness the operator
feels there, and the task time. Positions in the plane, SI units; one sample per tick.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from teleop_rt.config import SessionConfig, WallSpec


@dataclass(frozen=True)
class ExperimentGeometry:
    """The phases of a scripted task, from its config."""

    free_end_s: float  # the free-space stroke ends at the second waypoint
    wall_point: np.ndarray  # a point of the wall's surface (x, y), m
    wall_normal: np.ndarray  # its unit normal to free space
    wall_hold_s: tuple[float, float]  # the last half of the hold against the wall
    final_target: np.ndarray  # the task's last waypoint (x, y), m
    last_waypoint_s: float


def experiment_geometry(cfg: SessionConfig) -> ExperimentGeometry:
    """The phases of the config's hand-operator task: it must push a wall and hold there."""
    wps = getattr(cfg.operator, "waypoints", None)
    if not wps or len(wps) < 2:
        raise ValueError("the experiment needs a hand operator with waypoints")
    wall = next((e for e in cfg.environment if isinstance(e, WallSpec) and e.kind == "wall"), None)
    if wall is None:
        raise ValueError("the experiment has no wall")
    normal = np.asarray(wall.normal[:2], float) / np.linalg.norm(wall.normal[:2])
    point = np.asarray(wall.point_m[:2], float)
    hold = None
    for a, b in zip(wps, wps[1:], strict=False):
        inside = float((point - np.asarray(a.position_m[:2])) @ normal) > 0
        if a.position_m == b.position_m and inside:
            hold = (0.5 * (a.t_s + b.t_s), b.t_s)
    if hold is None:
        raise ValueError("the experiment has no hold against its wall")
    return ExperimentGeometry(
        free_end_s=wps[1].t_s,
        wall_point=point,
        wall_normal=normal,
        wall_hold_s=hold,
        final_target=np.asarray(wps[-1].position_m[:2], float),
        last_waypoint_s=wps[-1].t_s,
    )


def displayed_mass(v: np.ndarray, tau: np.ndarray, dt: float, window: np.ndarray) -> list[float]:
    """Per joint, the mass m of ``tau = m a + d v`` fitted by least squares over the ticks in
    ``window`` (a the tick's forward-difference acceleration): what the operator feels."""
    a = np.vstack([np.diff(v, axis=0), np.zeros((1, v.shape[1]))]) / dt
    out = []
    for j in range(v.shape[1]):
        x = np.column_stack([a[window, j], v[window, j]])
        coef, *_ = np.linalg.lstsq(x, tau[window, j], rcond=None)
        out.append(float(coef[0]))
    return out


def penetration(x: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Depth of tool positions x (ticks, 2) beyond a wall through ``point`` with unit
    ``normal`` to free space (> 0 inside)."""
    return (point - x) @ normal


def felt_stiffness(force_n: float, penetration_m: float) -> float:
    """The stiffness the operator feels: the force pushed into the wall over the HSI tool's
    penetration (infinite for none)."""
    return force_n / penetration_m if penetration_m > 0 else math.inf


def task_time(t: np.ndarray, errors_m: np.ndarray, tol_m: float) -> float:
    """The time from which ``errors_m`` (per tick) stays within ``tol_m`` to the end of the run:
    0 if always, NaN if not by the last tick."""
    outside = np.flatnonzero(errors_m > tol_m)
    if not len(outside):
        return 0.0
    if outside[-1] == len(t) - 1:
        return math.nan
    return float(t[outside[-1] + 1])
