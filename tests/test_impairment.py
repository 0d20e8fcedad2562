"""The impairment stage: each option's statistics match its parameters within sampling error,
the same seed gives the same decisions, and a trace file that is wrong is one clear line.

Tolerances: a rate measured over N independent packets is within 5 binomial standard errors
(sqrt(p (1 - p) / N)) of its parameter; where packets are not independent (bursty loss,
correlated jitter) the standard error is estimated from 100 batch means of the run itself.
Moments: the mean within 5 standard errors, the standard deviation within 5 of its own
(sigma / sqrt(2 N) for a normal sample); distributions by their CDF at a few points, each
within 5 binomial standard errors. With 5 standard errors a correct stage fails one test in
about 10^6 runs; the seeds are fixed, so a run is repeatable anyway."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from teleop_rt.com.impairment import Impairment, ImpairmentSpec, load_trace
from teleop_rt.errors import ConfigError
from tests.test_no_allocation import net_blocks

DT = 0.001


def decisions(spec: ImpairmentSpec, packets: int, stream: int = 0) -> dict[str, np.ndarray]:
    """Per packet sent at ticks 0, 1, ...: arrivals (0-2), their ticks and delays (ms)."""
    imp = Impairment(spec, DT, stream)
    count = np.zeros(packets, dtype=np.int64)
    tick = np.full((packets, 2), -1, dtype=np.int64)
    delay = np.full((packets, 2), np.nan)
    for s in range(packets):
        c = count[s] = imp.decide(s)
        tick[s, :c] = imp.arrivals[:c]
        delay[s, :c] = imp.delays_ms[:c]
    return {"count": count, "tick": tick, "delay": delay, "impairment": imp}


def within(measured: float, expected: float, se: float, k: float = 5.0) -> bool:
    return abs(measured - expected) <= k * se


def binomial_se(p: float, n: int) -> float:
    return math.sqrt(p * (1.0 - p) / n)


def batch_se(x: np.ndarray, batches: int = 100) -> float:
    means = x[: len(x) // batches * batches].reshape(batches, -1).mean(axis=1)
    return float(means.std(ddof=1) / math.sqrt(batches))


def test_no_impairment_delivers_every_packet_once_at_its_send_tick() -> None:
    d = decisions(ImpairmentSpec(), 1000)
    assert (d["count"] == 1).all() and (d["tick"][:, 0] == np.arange(1000)).all()


@pytest.mark.parametrize(
    "delay_ms, ticks", [(20.0, 20), (20.5, 21), (0.3, 1), (1e-12, 0), (19.999999, 20)]
)
def test_a_constant_delay_arrives_at_the_first_tick_at_or_after_it(delay_ms, ticks) -> None:
    d = decisions(ImpairmentSpec(delay_ms=delay_ms), 100)
    assert (d["tick"][:, 0] - np.arange(100) == ticks).all()


def test_the_same_seed_gives_the_same_decisions_and_another_seed_others() -> None:
    spec = dict(delay_ms=30, jitter_ms=8, correlation_percent=40, loss_percent=3,
                duplicate_percent=5, reorder_percent=4)  # fmt: skip
    a = decisions(ImpairmentSpec(seed=3, **spec), 5000)
    b = decisions(ImpairmentSpec(seed=3, **spec), 5000)
    c = decisions(ImpairmentSpec(seed=4, **spec), 5000)
    other_way = decisions(ImpairmentSpec(seed=3, **spec), 5000, stream=1)
    for name in ("count", "tick"):
        assert np.array_equal(a[name], b[name])
    assert np.array_equal(a["delay"], b["delay"], equal_nan=True)
    assert not np.array_equal(a["tick"], c["tick"])
    assert not np.array_equal(a["tick"], other_way["tick"])


def test_one_options_outcome_does_not_shift_anothers_draws() -> None:
    """A fixed number of draws per packet: adding loss leaves the survivors' delays alone."""
    jitter = decisions(ImpairmentSpec(seed=1, delay_ms=30, jitter_ms=5), 3000)
    lossy = decisions(ImpairmentSpec(seed=1, delay_ms=30, jitter_ms=5, loss_percent=20), 3000)
    kept = lossy["count"] == 1
    assert 0 < (~kept).sum() < 3000
    assert np.array_equal(lossy["delay"][kept, 0], jitter["delay"][kept, 0])


def test_independent_loss_rate() -> None:
    n, p = 200_000, 0.05
    d = decisions(ImpairmentSpec(seed=11, loss_percent=100 * p), n)
    lost = d["count"] == 0
    assert within(lost.mean(), p, binomial_se(p, n))
    assert d["impairment"].lost == lost.sum()


def burst_lengths(lost: np.ndarray) -> np.ndarray:
    """Lengths of the runs of consecutive losses."""
    edges = np.diff(np.concatenate([[0], lost.astype(np.int8), [0]]))
    return np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)


def test_gilbert_loss_rate_and_mean_burst_length() -> None:
    """The Gilbert model (1-h = 100 %, 1-k = 0): bursts are the bad state's sojourns,
    geometric with mean 1 / r; the loss rate is p / (p + r)."""
    n, p, r = 400_000, 0.02, 0.25
    ge = {"p_percent": 100 * p, "r_percent": 100 * r}
    d = decisions(ImpairmentSpec(seed=5, gilbert_elliott=ge), n)
    lost = (d["count"] == 0).astype(float)
    assert within(lost.mean(), p / (p + r), batch_se(lost))
    bursts = burst_lengths(lost > 0)
    burst_sd = math.sqrt(1.0 - r) / r
    assert within(bursts.mean(), 1.0 / r, burst_sd / math.sqrt(len(bursts)))


def test_gilbert_elliott_four_parameter_loss_rate() -> None:
    """Loss in both states: rate (p (1-h) + r (1-k)) / (p + r)."""
    n, p, r, loss_bad, loss_good = 400_000, 0.01, 0.10, 0.8, 0.01
    ge = {"p_percent": 100 * p, "r_percent": 100 * r, "loss_bad_percent": 100 * loss_bad,
          "loss_good_percent": 100 * loss_good}  # fmt: skip
    d = decisions(ImpairmentSpec(seed=6, gilbert_elliott=ge), n)
    lost = (d["count"] == 0).astype(float)
    expected = (p * loss_bad + r * loss_good) / (p + r)
    assert within(lost.mean(), expected, batch_se(lost))
    # bursts longer than independent loss at that rate would give (mean 1 / (1 - rate))
    assert burst_lengths(lost > 0).mean() > 1.0 / (1.0 - expected) + 1.0


def test_gilbert_elliott_with_p_alone_is_bernoulli() -> None:
    """netem: p alone sets r = 1 - p, 1-h = 1, 1-k = 0: independent loss at rate p."""
    n, p = 200_000, 0.03
    d = decisions(ImpairmentSpec(seed=7, gilbert_elliott={"p_percent": 100 * p}), n)
    lost = d["count"] == 0
    assert within(lost.mean(), p, binomial_se(p, n))
    assert within(burst_lengths(lost).mean(), 1.0 / (1.0 - p), 0.01)


def test_duplication_rate_and_the_copys_own_delay() -> None:
    n, p = 200_000, 0.03
    d = decisions(ImpairmentSpec(seed=8, delay_ms=40, jitter_ms=5, duplicate_percent=100 * p), n)
    twice = d["count"] == 2
    assert (d["count"] >= 1).all()
    assert within(twice.mean(), p, binomial_se(p, n))
    assert d["impairment"].duplicated == twice.sum()
    original, copy = d["delay"][twice, 0], d["delay"][twice, 1]
    assert (original != copy).mean() > 0.99  # its own draw
    assert within(copy.mean(), 40.0, 5.0 / math.sqrt(twice.sum()))


N_JITTER = 100_000


def jitter_delays(distribution: str, correlation: float = 0.0, seed: int = 9) -> np.ndarray:
    spec = ImpairmentSpec(seed=seed, delay_ms=50, jitter_ms=5, distribution=distribution,
                          correlation_percent=correlation)  # fmt: skip
    return decisions(spec, N_JITTER)["delay"][:, 0]


def assert_cdf(x: np.ndarray, cdf, points: list[float]) -> None:
    """The empirical CDF at each point within 5 binomial standard errors of ``cdf``."""
    for point in points:
        expected = cdf(point)
        assert within((x <= point).mean(), expected, binomial_se(expected, len(x))), point


def normal_cdf(x: float, mu: float = 50.0, sigma: float = 5.0) -> float:
    return 0.5 * math.erfc(-(x - mu) / (sigma * math.sqrt(2.0)))


def test_normal_jitter_moments_and_shape() -> None:
    x = jitter_delays("normal")
    n = len(x)
    assert within(x.mean(), 50.0, 5.0 / math.sqrt(n))
    assert within(x.std(), 5.0, 5.0 / math.sqrt(2 * n))
    skew = np.mean(((x - x.mean()) / x.std()) ** 3)
    assert within(skew, 0.0, math.sqrt(6.0 / n))
    assert_cdf(x, normal_cdf, [40.0, 45.0, 50.0, 55.0, 60.0])


def test_uniform_jitter_spans_delay_plus_minus_jitter() -> None:
    x = jitter_delays("uniform")
    n = len(x)
    assert 45.0 <= x.min() < 45.01 and 54.99 < x.max() <= 55.0
    assert within(x.mean(), 50.0, 5.0 / math.sqrt(3 * n))
    assert within(x.std(), 5.0 / math.sqrt(3.0), 0.01)
    assert_cdf(x, lambda v: (v - 45.0) / 10.0, [46.0, 48.0, 50.0, 52.0, 54.0])


def pareto_cdf(x: float, mu: float = 50.0, sigma: float = 5.0) -> float:
    """Shape-3 Pareto standardized (mean 1.5, std sqrt(3) / 2 before), at mean mu, std sigma."""
    p = 1.5 + (x - mu) / sigma * math.sqrt(3.0) / 2.0
    return 0.0 if p < 1.0 else 1.0 - p**-3.0


def test_pareto_jitter_mean_floor_and_tail() -> None:
    x = jitter_delays("pareto")
    n = len(x)
    assert within(x.mean(), 50.0, 5.0 / math.sqrt(n))
    floor = 50.0 - 5.0 / math.sqrt(3.0)  # (1 - 1.5) / (sqrt(3) / 2) standard deviations
    assert floor - 1e-9 <= x.min() < floor + 0.01
    assert_cdf(x, pareto_cdf, [48.0, 50.0, 55.0, 60.0, 70.0])
    assert (x > 70.0).mean() > 10 * (1 - normal_cdf(70.0))  # a heavy tail


def lag1(x: np.ndarray) -> tuple[float, float]:
    """Lag-1 correlation of a series and its batch-means standard error."""
    z = (x - x.mean()) / x.std()
    products = z[1:] * z[:-1]
    return float(products.mean()), batch_se(products)


@pytest.mark.parametrize("distribution", ["normal", "uniform", "pareto"])
def test_correlation_keeps_the_distribution_and_correlates_neighbours(distribution) -> None:
    """The draws are a Gaussian AR(1) chain mapped onto the distribution: neighbours' rank
    correlation is (6 / pi) asin(rho / 2) whatever the distribution (ranks survive the
    mapping), their plain correlation rho for the normal; the distribution is the same as
    without correlation."""
    rho = 0.6
    x = jitter_delays(distribution, correlation=100 * rho, seed=12)
    ranks = np.argsort(np.argsort(x)).astype(float)
    spearman, se = lag1(ranks)
    assert within(spearman, 6.0 / math.pi * math.asin(rho / 2.0), se)
    if distribution == "normal":
        pearson, se = lag1(x)
        assert within(pearson, rho, se)
    independent = jitter_delays(distribution)
    assert abs(lag1(independent)[0]) < 5.0 / math.sqrt(N_JITTER)
    for q in (0.1, 0.5, 0.9):  # same marginal as without correlation
        below = (x <= np.quantile(independent, q)).astype(float)
        assert within(below.mean(), q, batch_se(below)), q


def test_delays_are_clamped_to_zero_and_max_delay() -> None:
    d = decisions(ImpairmentSpec(seed=2, delay_ms=1, jitter_ms=5, max_delay_ms=3), 20_000)
    x = d["delay"][:, 0]
    assert x.min() == 0.0 and x.max() == 3.0
    assert (d["tick"][:, 0] - np.arange(20_000)).max() == 3


def test_reorder_sends_its_fraction_at_once() -> None:
    n, p = 100_000, 0.1
    d = decisions(ImpairmentSpec(seed=13, delay_ms=20, reorder_percent=100 * p), n)
    at_once = d["tick"][:, 0] == np.arange(n)
    assert within(at_once.mean(), p, binomial_se(p, n))
    assert (d["tick"][~at_once, 0] - np.arange(n)[~at_once] == 20).all()
    assert d["impairment"].reordered == at_once.sum()


def test_reorder_with_a_gap_reorders_every_gapth_packet() -> None:
    """netem: 'reorder 100% gap 5' sends every 5th packet at once, the others delayed."""
    d = decisions(ImpairmentSpec(delay_ms=10, reorder_percent=100, reorder_gap=5), 100)
    at_once = np.flatnonzero(d["tick"][:, 0] == np.arange(100))
    assert list(at_once) == list(range(4, 100, 5))


def test_reorder_gap_counts_only_packets_not_lost() -> None:
    d = decisions(ImpairmentSpec(seed=3, delay_ms=10, reorder_percent=100, reorder_gap=3,
                                 loss_percent=30), 3000)  # fmt: skip
    kept = np.flatnonzero(d["count"] == 1)
    at_once = d["tick"][kept, 0] == kept
    assert list(np.flatnonzero(at_once)) == list(range(2, len(kept), 3))


def test_a_step_down_in_delay() -> None:
    d = decisions(ImpairmentSpec(delay_ms=40, delay_step={"at_s": 1.0, "delay_ms": 10}), 2000)
    lag = d["tick"][:, 0] - np.arange(2000)
    assert (lag[:1000] == 40).all() and (lag[1000:] == 10).all()


def test_decide_allocates_nothing_it_keeps() -> None:
    spec = ImpairmentSpec(seed=1, delay_ms=20, jitter_ms=4, distribution="pareto",
                          correlation_percent=30, gilbert_elliott={"p_percent": 1, "r_percent": 30},
                          duplicate_percent=2, reorder_percent=2)  # fmt: skip
    imp = Impairment(spec, DT)
    tick = iter(range(10**9))
    assert net_blocks(lambda: imp.decide(next(tick)), 10_000) < 100


# --- trace replay -------------------------------------------------------------------------
def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "trace.csv"
    path.write_text(text)
    return path


def test_a_trace_replays_per_packet_and_repeats(tmp_path) -> None:
    path = write(
        tmp_path, "# recorded\nsend_tick,delay_ms\n100,2.5\n101,lost\n102,1\n102,4\n103,0\n"
    )
    d = decisions(ImpairmentSpec(trace=path), 8)
    assert list(d["count"]) == [1, 0, 2, 1] * 2
    assert list(d["tick"][:, 0]) == [3, -1, 3, 3, 7, -1, 7, 7]
    assert list(d["tick"][:, 1]) == [-1, -1, 6, -1, -1, -1, 10, -1]
    assert d["delay"][2, 1] == 4.0
    imp = d["impairment"]
    assert (imp.lost, imp.duplicated) == (2, 2)


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("0,1\n1,2,3\n", 2, "expected 'send_tick,delay_ms'"),
        ("0,1\nx,2\n", 2, "send_tick 'x' is not a whole number"),
        ("0,1\n1,fast\n", 2, "delay_ms 'fast' is neither a number nor 'lost'"),
        ("0,1\n1,-1\n", 2, "outside [0, max_delay_ms = 1000]"),
        ("0,1\n1,nan\n", 2, "outside"),
        ("0,1\n1,2000\n", 2, "outside"),
        ("0,1\n\n2,1\n", 3, "send_tick 2 where 1 comes next"),
        ("5,1\n4,1\n", 2, "send_tick 4 where 6 comes next"),
        ("0,lost\n0,1\n", 2, "send_tick 0 again"),
        ("0,1\n0,lost\n", 2, "send_tick 0 again"),
        ("0,1\n0,1\n0,1\n", 3, "send_tick 0 again"),
    ],
)
def test_a_malformed_trace_is_one_line_naming_its_line(tmp_path, text, line, words) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        Impairment(ImpairmentSpec(trace=path), DT)
    message = str(err.value)
    assert f"{path}, line {line}: " in message and words in message and "\n" not in message


def test_an_empty_or_missing_trace_is_one_line(tmp_path) -> None:
    with pytest.raises(ConfigError, match="no packets in it"):
        load_trace(write(tmp_path, "send_tick,delay_ms\n# nothing\n"), 1000)
    with pytest.raises(ConfigError, match="absent.csv: no such file"):
        load_trace(tmp_path / "absent.csv", 1000)


# --- the config models --------------------------------------------------------------------
@pytest.mark.parametrize(
    "fields, words",
    [
        ({"loss_percent": 1, "gilbert_elliott": {"p_percent": 1}}, "not both"),
        ({"trace": "t.csv", "jitter_ms": 1}, "trace replaces jitter_ms"),
        ({"reorder_percent": 5}, "needs a delay_ms"),
        ({"gilbert_elliott": {"p_percent": 1, "r_percent": 0}}, "r_percent must be > 0"),
        ({"loss_percent": 101}, "less than or equal to 100"),
        ({"correlation_percent": 100}, "less than 100"),
        ({"distribution": "lognormal"}, "normal"),
        ({"jitter": 1}, "Extra inputs"),
        ({"delay_ms": float("nan")}, "finite"),
        ({"delay_ms": 1500}, "1500 ms is beyond max_delay_ms"),
        ({"delay_step": {"at_s": 1, "delay_ms": 30}, "max_delay_ms": 20}, "30 ms is beyond"),
    ],
)
def test_the_config_model_refuses_what_cannot_be_meant(fields, words) -> None:
    with pytest.raises(ValidationError, match=words):
        ImpairmentSpec(**fields)


def test_a_relative_trace_is_resolved_against_the_config_folder(tmp_path) -> None:
    spec = ImpairmentSpec(trace="traces/a.csv").with_paths_resolved(tmp_path)
    assert spec.trace == (tmp_path / "traces" / "a.csv").resolve()
    absolute = ImpairmentSpec(trace=tmp_path / "b.csv")
    assert absolute.with_paths_resolved(Path("/elsewhere")) is absolute
