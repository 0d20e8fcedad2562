"""The experiment figures (teleop_rt.analysis.experiment) against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.analysis import experiment
from tests.conftest import CONFIGS

DT = 1e-3


def test_the_displayed_mass_fit_recovers_m_of_tau_equals_m_a_plus_d_v() -> None:
    """tau = m a + d v exactly (a the forward difference of v): m recovered to rounding, per
    joint, whatever d."""
    t = np.arange(4000) * DT
    v = np.column_stack([0.3 * np.sin(2.0 * t), 0.1 * np.sin(5.0 * t) + 0.05 * t])
    a = np.vstack([np.diff(v, axis=0), np.zeros((1, 2))]) / DT
    m, d = np.array([0.35, 1.7]), np.array([0.2, 0.05])
    tau = a * m + v * d
    window = t < 3.0  # (the last tick's acceleration is not known: outside the window)
    fit = experiment.displayed_mass(v, tau, DT, window)
    np.testing.assert_allclose(fit, m, rtol=1e-9)


def test_penetration_and_felt_stiffness() -> None:
    point, normal = np.array([0.4, 0.0]), np.array([-1.0, 0.0])  # free space at x < 0.4
    x = np.array([[0.39, 0.1], [0.41, 0.0], [0.4025, -0.3]])
    np.testing.assert_allclose(experiment.penetration(x, point, normal), [-0.01, 0.01, 0.0025])
    assert experiment.felt_stiffness(10.0, 0.0025) == pytest.approx(4000.0)
    assert experiment.felt_stiffness(10.0, 0.0) == math.inf


def test_task_time_is_when_the_error_stays_within_the_tolerance() -> None:
    t = np.arange(10) * 0.5
    err = np.array([9, 9, 1, 9, 1, 1, 1, 1, 1, 1], float) * 1e-3
    assert experiment.task_time(t, err, 2e-3) == 2.0  # from tick 4 on (back out at tick 3)
    assert experiment.task_time(t, np.zeros(10), 2e-3) == 0.0
    assert math.isnan(experiment.task_time(t, np.r_[np.zeros(9), 1.0], 2e-3))


def test_the_paper_experiments_geometry_from_its_config() -> None:
    cfg = config.load(CONFIGS / "paper_experiment.yaml")
    g = experiment.experiment_geometry(cfg)
    wall = next(e for e in cfg.environment if e.kind == "wall")
    assert g.free_end_s == cfg.operator.waypoints[1].t_s
    np.testing.assert_allclose(g.wall_point, wall.point_m[:2])
    assert np.linalg.norm(g.wall_normal) == pytest.approx(1.0)
    lo, hi = g.wall_hold_s
    assert lo < hi <= g.last_waypoint_s
    with pytest.raises(ValueError, match="no wall"):
        experiment.experiment_geometry(config.load(CONFIGS / "free_space.yaml"))
