"""A posture or orientation gain near or beyond the TO's sampled velocity loop's limit is refused.

The correction k (target - x) in the velocity reference closes, per direction, the loop of
teleop_rt.analysis.contact with K / b = k: stable only for k < (4 T2 - 2 dt) / dt^2 (Jury). On
configs/task_space/scara_ur5_plane.yaml (T2 = 5 ms at 1 kHz) that is 18 000 1/s; a site refuses
half of it and more (site.TASK_GAIN_FRACTION: near the limit the loop rings). Found from
outside: a gain of 1e308 passed ``check`` and the run stopped on its safety guard."""

from __future__ import annotations

import pytest

from teleop_rt import config, site
from teleop_rt.analysis.contact import contact_stiffness_limit
from teleop_rt.cli import main
from teleop_rt.errors import ConfigError
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_cli import assert_one_error_line

PLANE = CONFIGS / "task_space" / "scara_ur5_plane.yaml"  # a UR5 TO: 4 joints to spare
POSE = CONFIGS / "task_space" / "ur5_panda_pose.yaml"
LIMIT = contact_stiffness_limit(1.0, 0.005, 1.0, 0.001)  # T2 = M2/c2 = 5 ms: 18 000 1/s


def test_the_limit_is_the_configs_and_its_closed_form() -> None:
    cfg = config.load(PLANE, [])
    t2 = [m / c for m, c in zip(cfg.to.virtual_mass, cfg.to.controller.kp, strict=True)]  # type: ignore[arg-type]
    assert t2 == pytest.approx([0.005] * 6)
    assert LIMIT == pytest.approx((4 * 0.005 - 2 * 0.001) / 0.001**2)  # 18 000


@pytest.mark.parametrize(
    "path,key", [(PLANE, "posture_gain_per_s"), (POSE, "orientation_gain_per_s")]
)
@pytest.mark.parametrize("gain", ["1e308", str(LIMIT), str(site.TASK_GAIN_FRACTION * LIMIT)])
def test_check_refuses_a_gain_at_or_beyond_the_limit(path, key, gain, capsys) -> None:
    code = main(["check", str(path), "--set", f"mapping.{key}={gain}"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert_one_error_line(err, f"mapping.{key} = ", "1.8e+04 1/s at rate_hz = 1000",
                          "the correction would ring or be unstable")  # fmt: skip


def run_to_the_end(gain: float) -> str | None:
    """The plane session (its 6 s) with the posture gain; the safety stop's reason or None."""
    cfg = config.load(PLANE, [f"mapping.posture_gain_per_s={gain}"])
    return Session(cfg).run().stopped_early


def test_the_limit_separates_the_runs_that_hold_from_those_that_stop(monkeypatch) -> None:
    """The physics behind the line: just under the refused fraction the run ends normally; with
    the check switched off, at 99 % of the limit the loop rings into a safety stop (a review's
    finding: 0.5 s had hidden it) and at 110 % it diverges."""
    assert run_to_the_end(0.95 * site.TASK_GAIN_FRACTION * LIMIT) is None
    monkeypatch.setattr(site, "require_stable_task_gains", lambda cfg, n: None)
    assert run_to_the_end(0.99 * LIMIT) is not None
    assert run_to_the_end(1.1 * LIMIT) is not None


def test_a_gain_below_the_limit_passes() -> None:
    cfg = config.load(PLANE, ["mapping.posture_gain_per_s=8999"])
    site.require_stable_task_gains(cfg, 6)
    with pytest.raises(ConfigError):
        site.require_stable_task_gains(config.load(PLANE, ["mapping.posture_gain_per_s=9001"]), 6)


def test_a_joint_past_its_own_loop_limit_bounds_no_gain() -> None:
    """dt / T2 = 2 (T2 = 0.5 ms at 1 kHz: the velocity loop itself at its limit, K_max = 0) is
    the loop's matter, not the gain's: the default orientation gain is not refused for it (it
    was, in a pose pair test with a UR5's masses and kp 50); the other joints still bound it."""
    sets = ["to.virtual_mass=[1.0, 1.0, 0.5, 0.5, 0.1, 0.1, 0.025]", "to.controller.kp=50"]
    cfg = config.load(POSE, sets)
    site.require_stable_task_gains(cfg, 7)  # joints 0-5: T2 >= 2 ms, limits >= 6 000 1/s
    with pytest.raises(ConfigError, match="T2 = M2/c2 = 0.002 s at joint 4"):
        site.require_stable_task_gains(
            config.load(POSE, [*sets, "mapping.orientation_gain_per_s=7000"]), 7
        )
