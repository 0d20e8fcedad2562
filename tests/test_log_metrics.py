"""log_metrics: the live summary's figures from a log, bit for bit."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from log_fixtures import field_slice, synthetic_rows, write_synthetic_log

from teleop_rt.loop import TimingStats
from teleop_rt.recording.metrics import format_metrics, log_metrics, metrics_main
from teleop_rt.recording.reader import LogData, LogError, read_log
from teleop_rt.recording.schema import LogLayout
from teleop_rt.transparency_tick import TransparencyAccumulator


def accumulate(log, ticks: slice, start: int = 0) -> TransparencyAccumulator:
    """The live accumulator fed rows[ticks], its offset taken at tick ``start``."""
    q_h, q_t = log.field("/hsi", "q"), log.field("/to", "q")
    tau_h, tau_t = log.field("/hsi", "tau_ext"), log.field("/to", "tau_ext")
    offset = (q_h[start] - q_t[start]).tolist()
    acc = TransparencyAccumulator(len(offset), log.dt, offset)
    for a, b, c, d in zip(q_h[ticks], q_t[ticks], tau_h[ticks], tau_t[ticks], strict=True):
        acc.add(a.tolist(), b.tolist(), c.tolist(), [-x for x in d.tolist()])
    return acc


@pytest.mark.parametrize("seed, n, scale", [(0, 2, 1.0), (1, 3, 1e3), (2, 1, 1e-4), (3, 6, 10.0)])
def test_transparency_bit_equal_to_live_accumulator(tmp_path, seed, n, scale):
    """Random signals of several magnitudes: the same floats as the live loop, not just close."""
    rng = np.random.default_rng(seed)
    ticks = 3000
    log = write_synthetic_log(
        tmp_path / "a.mcap", ticks, n, seed=seed, rate_hz=500,
        hsi_q=scale * rng.standard_normal((ticks, n)),
        to_q=scale * rng.standard_normal((ticks, n)),
        hsi_tau_ext=scale * rng.standard_normal((ticks, n)),
        to_tau_ext=scale * rng.standard_normal((ticks, n)),
    )  # fmt: skip
    m = log_metrics(read_log(log.path))
    acc = accumulate(log, slice(None))
    assert m["t_p"] == acc.t_p.tolist() and m["t_tau"] == acc.t_tau.tolist()  # exact float equality
    assert m["t_p_total"] == float(sum(acc.t_p)) and m["t_tau_total"] == float(sum(acc.t_tau))
    assert m["ticks"] == ticks and m["simulated_time_s"] == ticks * (1.0 / 500)


@settings(max_examples=60, deadline=None)
@given(
    ticks=st.integers(1, 400),
    n=st.integers(1, 4),
    exponent=st.integers(-6, 6),
    rate=st.sampled_from([100, 1000, 4000]),
    seed=st.integers(0, 2**32 - 1),
)
def test_transparency_property(ticks, n, exponent, rate, seed):
    """Any rows (in memory, no file): log_metrics == the live accumulator, bit for bit."""
    layout = LogLayout(n, 0)
    rows = synthetic_rows(layout, ticks, 1.0 / rate, seed=seed)
    rng = np.random.default_rng(seed)
    for topic, name in (("/hsi", "q"), ("/to", "q"), ("/hsi", "tau_ext"), ("/to", "tau_ext")):
        rows[:, field_slice(layout, topic, name)] = 10.0**exponent * rng.standard_normal((ticks, n))
    cols = layout.columns()
    topics = {t.name: layout.encode(rows, t, cols[t.name]) for t in layout.topics}
    meta = {"rate_hz": str(rate), "name": "x", "delay_ticks": "0"}
    data = LogData(None, meta, layout, None, {}, None, False, None, topics)
    q_h, q_t = topics["/hsi"]["q"], topics["/to"]["q"]
    acc = TransparencyAccumulator(n, 1.0 / rate)
    for k in range(ticks):
        tau_e = [-x for x in topics["/to"]["tau_ext"][k].tolist()]
        acc.add(q_h[k].tolist(), q_t[k].tolist(), topics["/hsi"]["tau_ext"][k].tolist(), tau_e)
    m = log_metrics(data)
    assert m["t_p"] == acc.t_p.tolist() and m["t_tau"] == acc.t_tau.tolist()


def test_pairwise_sum_would_differ(tmp_path):
    """Why the sequential sum: numpy's pairwise sum is not the live figure (so the bit-equality
    test above can fail)."""
    rng = np.random.default_rng(7)
    ticks, n = 4000, 4
    log = write_synthetic_log(tmp_path / "a.mcap", ticks, n, hsi_q=rng.random((ticks, n)))
    data = read_log(log.path)
    e = data.topics["/hsi"]["q"] - data.topics["/to"]["q"]
    e = e - e[0]
    terms = e * e * data.dt
    pairwise = [float(np.sum(np.ascontiguousarray(terms[:, j]))) for j in range(n)]
    assert pairwise != log_metrics(data)["t_p"]
    assert log_metrics(data)["t_p"] == accumulate(log, slice(None)).t_p.tolist()


def test_whole_log_equals_stored_live_summary(tmp_path):
    log = write_synthetic_log(tmp_path / "a.mcap", 2500, 3, 2, chunk_size=8192)
    m = log_metrics(read_log(log.path))
    for key in ("name", "ticks", "simulated_time_s", "delay_ticks", "t_p", "t_tau"):
        assert m[key] == log.summary[key], key
    for key in ("t_p_total", "t_tau_total", "channel_energy_j", "min_channel_energy_j"):
        assert m[key] == log.summary[key], key
    live = dict(log.summary["timing"])
    live.pop("wall_s")
    assert m["timing"] == live


def test_closed_form(tmp_path):
    """q_h - q_t - offset = c after the first tick, tau_h - tau_e = d: T_p = (N-1) c^2 dt,
    T_tau = N d^2 dt."""
    ticks, n, dt = 4000, 2, 1e-3
    c, d = np.array([0.01, -0.25]), np.array([0.5, 2.0])
    t = np.arange(ticks)[:, None] * dt
    base = 0.3 * np.sin(2 * np.pi * t) + np.array([0.1, 0.7])
    q_t = base.copy()
    q_t[1:] -= c  # tick 0 sets the offset (0 here); then a constant error c
    tau_h = np.cos(3 * t) * np.array([1.0, 2.0])
    log = write_synthetic_log(
        tmp_path / "a.mcap", ticks, n, hsi_q=base, to_q=q_t, hsi_tau_ext=tau_h,
        to_tau_ext=d - tau_h,  # tau_e = -(to tau_ext) = tau_h - d
    )  # fmt: skip
    m = log_metrics(read_log(log.path))
    np.testing.assert_allclose(m["t_p"], (ticks - 1) * c**2 * dt, rtol=1e-12)
    np.testing.assert_allclose(m["t_tau"], ticks * d**2 * dt, rtol=1e-12)


def test_offset_is_the_session_start(tmp_path):
    """A constant q_h - q_t is removed by the offset: T_p = 0 exactly."""
    ticks = 500
    q = np.linspace(0, 1, ticks)[:, None] * np.ones(2)
    log = write_synthetic_log(tmp_path / "a.mcap", ticks, hsi_q=q + 0.5, to_q=q - 0.25)
    m = log_metrics(read_log(log.path))
    assert max(m["t_p"]) < 1e-28


def run_json(capsys, path, **kwargs) -> dict:
    assert metrics_main(path, as_json=True, **kwargs) == 0
    return json.loads(capsys.readouterr().out)


def test_window(tmp_path, capsys):
    """from <= t < to; offset of the session start (tick 0), not of the window."""
    log = write_synthetic_log(tmp_path / "a.mcap", 3000, chunk_size=4096)
    m = run_json(capsys, log.path, t_from=0.75, t_to=2.0)
    acc = accumulate(log, slice(750, 2000), start=0)
    assert m["ticks"] == 1250 and m["first_tick"] == 750
    assert m["t_p"] == acc.t_p.tolist() and m["t_tau"] == acc.t_tau.tolist()
    energy = log.field("/channel", "total_energy")[750:2000, 0]
    assert m["channel_energy_j"] == energy[-1]
    assert m["min_channel_energy_j"] == min(0.0, energy.min())
    assert m["window_s"] == [0.75, 2.0] and m["live_summary_agrees"] is None
    compute = log.field("/timing", "compute_ns")[750:2000, 0].astype(np.int64)
    assert m["timing"]["compute_us"]["p99"] == np.percentile(compute, 99) / 1e3
    # the window's own first tick as offset would give other figures
    assert m["t_p"] != accumulate(log, slice(750, 2000), start=750).t_p.tolist()
    with pytest.raises(LogError, match="window 10 s to the end holds no ticks"):
        metrics_main(log.path, as_json=True, t_from=10.0)  # zeros would be no result


def test_timing_equals_timing_stats(tmp_path):
    rng = np.random.default_rng(3)
    ticks = 1001
    compute = rng.integers(1, 10**7, ticks)
    late = rng.integers(0, 10**6, ticks)
    missed = rng.random(ticks) < 0.1
    log = write_synthetic_log(
        tmp_path / "a.mcap", ticks, timing_compute_ns=compute, timing_lateness_ns=late,
        timing_missed=missed,
    )  # fmt: skip
    stats = TimingStats(ticks, 1_000_000)  # the synthetic log's period (1 kHz)
    for c, la, mi in zip(compute.tolist(), late.tolist(), missed.tolist(), strict=True):
        stats.add(c, la, mi)
    assert log_metrics(read_log(log.path))["timing"] == stats.summary()
    assert stats.summary()["missed_deadlines"] == int(missed.sum()) > 0


def test_channel_energy_minimum_starts_at_zero(tmp_path):
    ticks = 300
    energy = 1.0 + np.linspace(0, 1, ticks)
    log = write_synthetic_log(tmp_path / "a.mcap", ticks, channel_total_energy=energy)
    m = log_metrics(read_log(log.path))
    assert m["channel_energy_j"] == 2.0 and m["min_channel_energy_j"] == 0.0
    energy[100] = -0.125
    log = write_synthetic_log(tmp_path / "b.mcap", ticks, channel_total_energy=energy)
    assert log_metrics(read_log(log.path))["min_channel_energy_j"] == -0.125


def test_truncated_log(tmp_path, capsys):
    log = write_synthetic_log(tmp_path / "k.mcap", 3000, chunk_size=4096, finish=False)
    data = read_log(log.path)
    m = log_metrics(data)
    acc = accumulate(log, slice(0, data.ticks))
    assert m["truncated"] and m["t_p"] == acc.t_p.tolist() and m["ticks"] == data.ticks
    assert metrics_main(log.path) == 0
    captured = capsys.readouterr()
    assert "log cut short" in captured.out and "warning" in captured.err


def test_text_output(tmp_path, capsys):
    log = write_synthetic_log(tmp_path / "a.mcap", 1000)
    assert metrics_main(log.path) == 0
    out = capsys.readouterr().out
    assert "live summary                      agrees exactly" in out
    assert "ticks started over a period late  " in out  # a gap after the longest label
    assert f"{log.summary['t_p_total']:.6g}" in out and "1000 (1.000 s)" in out
    m = log_metrics(read_log(log.path))
    m["live_summary_agrees"] = False
    assert "DIFFERS" in format_metrics(m)
