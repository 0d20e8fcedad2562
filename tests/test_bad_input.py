"""Bad input from the outside (issue 18, "one clear line, never a traceback"): configs and
overrides, damaged logs, empty windows, broken URDFs and early signals. Every case drives the
CLI (``main(argv)`` or a subprocess) and wants exit code 2 and one ``teleop-rt: error:`` line."""

from __future__ import annotations

from pathlib import Path

import pytest

from teleop_rt.cli import main
from tests.test_cli import assert_one_error_line

ROOT = Path(__file__).resolve().parents[1]
PAPER = str(ROOT / "configs" / "paper_experiment.yaml")


def cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def assert_refused(argv: list[str], capsys: pytest.CaptureFixture[str], *named: str) -> str:
    code, _, err = cli(argv, capsys)
    assert code == 2, err
    assert_one_error_line(err, *named)
    return err


# --- config values ----------------------------------------------------------------------------
@pytest.mark.parametrize("side", ["to", "hsi"])
def test_zero_p_gain_is_refused_naming_the_key(side, capsys) -> None:
    assert_refused(
        ["check", PAPER, "--set", f"{side}.controller.kp=0"], capsys, f"{side}.controller.kp"
    )
    assert_refused(["run", PAPER, "--set", f"{side}.controller.kp=[20, 0]"], capsys, "kp")


def test_zero_kp_of_a_pid_has_no_contact_limit(capsys) -> None:
    """A PID without its P term is a controller (pure I): the P contact analysis sets no limit
    and warns about nothing, even against the stiff wall."""
    sets = ["--set", "to.controller.kind=pid", "--set", "to.controller.kp=0"]
    sets += ["--set", "to.controller.ki=5"]
    code, out, err = cli(["check", str(ROOT / "configs" / "stiff_wall.yaml"), *sets], capsys)
    assert code == 0 and "ok" in out and err == "", err


TICK_COUNTS = [
    "safety.stale_ticks",
    "safety.saturation_stop_ticks",
    "safety.tracking_error_ticks",
    "safety.stop_max_ticks",
]


@pytest.mark.parametrize("key", TICK_COUNTS)
@pytest.mark.parametrize("value", [2**63, 10**8 + 1, 2**70])
def test_tick_counts_have_an_upper_bound(key, value, capsys) -> None:
    assert_refused(["check", PAPER, "--set", f"{key}={value}"], capsys, key, "less than")


def test_a_long_seed_is_refused(capsys) -> None:
    # 5000 digits: more than Python converts; 4000: converted, above the bound
    err = assert_refused(["check", PAPER, "--set", "seed=" + "9" * 5000], capsys, "seed")
    assert len(err) < 300, "the value is not echoed whole"
    assert_refused(["check", PAPER, "--set", "seed=" + "9" * 4000], capsys, "seed", "less than")
    assert_refused(["check", PAPER, "--set", f"seed={2**63}"], capsys, "seed")


def test_a_long_integer_in_a_config_file_is_one_line(tmp_path, capsys) -> None:
    text = Path(PAPER).read_text().replace("../robots", str(ROOT / "robots"))
    path = tmp_path / "seed.yaml"
    path.write_text(text + f"\nseed: {'7' * 5000}\n")
    assert_refused(["check", str(path)], capsys, str(path), "integer too long")
