"""The causal floor of T_p (tools/transparency_study.py, issue 23): an oracle TO at the HSI's
position of the newest sample it can know, on hand-made traces against closed forms.

A ramp q_h = q0 + v t (two joints, so v^2 = |v|^2 sums over them as eq 18's total does) held by
the oracle at the sample of sender tick info(k) is off by |v| (k - info(k)) dt at tick k, so
T_p = |v|^2 dt^3 sum_k (k - info(k))^2. The traces replay through the link's own Impairment.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import transparency_study as ts  # noqa: E402

from teleop_rt.com.impairment import ImpairmentSpec  # noqa: E402

DT = 1e-3
V = np.array([0.3, -0.4])  # rad/s: |v|^2 = 0.25
Q0 = np.array([0.7, -1.2])  # the start: alpha is measured from it


def ramp(ticks: int) -> np.ndarray:
    return Q0 + np.outer(np.arange(ticks) * DT, V)


def trace(tmp_path: Path, delays_ms: list[float]) -> ImpairmentSpec:
    path = tmp_path / "trace.csv"
    rows = (f"{s},{d:.3f}" for s, d in enumerate(delays_ms))
    path.write_text("\n".join(["send_tick,delay_ms", *rows]) + "\n")
    return ImpairmentSpec(trace=path)


def floor(spec: ImpairmentSpec | None, d_ticks: int, playout: str, ticks: int) -> float:
    lag = ts.link_lags(spec, DT, ticks)
    return ts.causal_floor(ramp(ticks), DT, ts.info_ticks(ticks, d_ticks, playout, lag))


def test_fixed_playout_outages_hold_the_last_packet_in_time(tmp_path: Path) -> None:
    """Fixed D = 10 ticks; every P = 100 packets the last L = 30 are late (15 ms > D: as the
    study's outages, never played). Ticks k < D hold the start (lag k); after, the lag is D
    plus the run of late packets ending at k - D (m = 1 .. L in each of the H holds, 0
    elsewhere): T_p = |v|^2 dt^3 (sum_{k<D} k^2 + (N - D - H L) D^2 + H sum_{m=1..L} (D + m)^2)."""
    d, p, hold, holds = 10, 100, 30, 5
    spec = trace(tmp_path, [0.0] * (p - hold) + [15.0] * hold)
    n = d + holds * p  # the sender ticks k - D cover exactly H periods
    closed = (V @ V) * DT**3 * (
        sum(k * k for k in range(d))
        + (n - d - holds * hold) * d * d
        + holds * sum((d + m) ** 2 for m in range(1, hold + 1))
    )
    assert floor(spec, d, "fixed", n) == pytest.approx(closed, rel=1e-12)
    # the clean link at the same D (the delay alone) is well below it: the outages matter
    clean = (V @ V) * DT**3 * (sum(k * k for k in range(d)) + (n - d) * d * d)
    assert floor(None, d, "fixed", n) == pytest.approx(clean, rel=1e-12)
    assert closed > 2 * clean


def test_newest_playout_knows_a_late_packet_when_it_arrives(tmp_path: Path) -> None:
    """A constant 25 ms (25 ticks) beyond D = 10: ``fixed`` never plays a packet (the oracle
    keeps the start: T_p = |v|^2 dt^3 sum_{k<N} k^2); ``newest`` knows each one 25 ticks after
    it was sent (T_p = |v|^2 dt^3 (sum_{k<25} k^2 + (N - 25) 25^2))."""
    n, lag = 400, 25
    spec = trace(tmp_path, [25.0])
    never = (V @ V) * DT**3 * sum(k * k for k in range(n))
    late = (V @ V) * DT**3 * (sum(k * k for k in range(lag)) + (n - lag) * lag * lag)
    assert floor(spec, 10, "fixed", n) == pytest.approx(never, rel=1e-12)
    assert floor(spec, 10, "newest", n) == pytest.approx(late, rel=1e-12)


def test_a_lost_packet_is_never_known(tmp_path: Path) -> None:
    """Every other packet lost (fixed D = 4, no delay): at k >= D the lag is D on a delivered
    sender tick, D + 1 on a lost one."""
    path = tmp_path / "lossy.csv"
    path.write_text("send_tick,delay_ms\n0,0\n1,lost\n")
    n, d = 204, 4
    closed = (V @ V) * DT**3 * (
        sum(k * k for k in range(d)) + (n - d) // 2 * (d * d + (d + 1) ** 2)
    )
    assert floor(ImpairmentSpec(trace=path), d, "fixed", n) == pytest.approx(closed, rel=1e-12)


@pytest.mark.parametrize("channel", ["reflected", "zero"])
def test_before_a_delay_step_the_run_is_the_constant_delay_link_s(channel: str) -> None:
    """T_tau's prefix floor: free-space sweeps, 40 ms stepping down to 8 ms at 1 s (newest,
    D = 2 ms): up to the step the run is, tick for tick, the constant-40 ms link's, so its T_tau
    there is the floor's bit for bit, and the whole run's is at least that."""
    down = {"delay_ms": 40, "delay_step": {"at_s": 1.0, "delay_ms": 8}}
    step = ts.Net("step", "newest", 2, down)
    row = ts.run("free-space sweeps", step, channel, 2.0)
    floor_tau, at_s = ts.t_tau_prefix_floor("free-space sweeps", step, channel, 2.0)
    assert floor_tau == row["t_tau_so_far"][round(at_s / row["dt"]) - 1]
    assert 0.0 < floor_tau < row["t_tau"]
    with pytest.raises(ValueError, match="no delay step"):
        ts.t_tau_prefix_floor("free-space sweeps", ts.Net("clean", "newest", 2), channel)
