"""``check`` refuses a channel that stops in free space on a clean link (issue 23): the
unfiltered wave channel at short delays rings up in free space until the safety layer stops it
on tracking error (teleop_rt.analysis.free_space_probe). One line, the reason, exit 2."""

from __future__ import annotations

import pytest

from teleop_rt.cli import main
from tests.conftest import CONFIGS

FREE = str(CONFIGS / "free_space.yaml")


def check(capsys: pytest.CaptureFixture[str], *sets: str) -> tuple[int, str]:
    argv = ["check", FREE]
    for s in sets:
        argv += ["--set", s]
    code = main(argv)
    err = capsys.readouterr().err.strip()
    return code, err


def test_check_refuses_the_unfiltered_wave_channel_that_stops_in_free_space(capsys) -> None:
    code, err = check(capsys, "channel.delay_ms=1", "channel.wave_filter_hz=null")
    assert code == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "channel.wave_filter_hz" in err and "stops in free space" in err
    assert "does not follow its commanded acceleration" in err


@pytest.mark.parametrize("sets", [("channel.delay_ms=1",),  # the 30 Hz filter damps it
                                  ("channel.delay_ms=100", "channel.wave_filter_hz=null")])
def test_check_accepts_what_holds_still_in_free_space(sets, capsys) -> None:
    code, err = check(capsys, *sets)
    assert code == 0, err
