"""TickClock and TimingStats against a fake clock: no wall-clock time is measured or asserted.

The fake clock's time is an integer in ns. Reading it costs ``read_ns`` (time moves on by that
much after each read, as a real clock read would take time; this is what lets the spin loop
end), ``sleep`` advances it by exactly the requested time, and ``work`` stands for a tick's
computation.
"""

from __future__ import annotations

import gc
import struct

import pytest

from teleop_rt.errors import SafetyStop, TeleopError
from teleop_rt.loop import (
    OVERRUN_POLICIES,
    OVERSLEEP_STEP_NS,
    OverrunStop,
    RealtimeGrant,
    TickClock,
    TimingStats,
    hold_wakeup_latency,
)

PERIOD = 1_000_000  # 1 kHz
SPIN = 200_000
READ = 1_000  # divides SPIN and PERIOD: the spin lands exactly on the deadline
START = 5_000_000_000


class FakeClock:
    def __init__(self, t0: int = START, read_ns: int = READ, max_reads: int = 1_000_000) -> None:
        self.t = t0
        self.read_ns = read_ns
        self.max_reads = max_reads
        self.reads = 0
        self.last_read: int | None = None
        self.sleep_targets: list[int] = []  # last clock reading + requested sleep, in ns

    def now_ns(self) -> int:
        self.reads += 1
        if self.reads > self.max_reads:  # a spin that never ends fails instead of hanging
            raise AssertionError("the clock was read too often: the spin loop does not end")
        value = self.last_read = self.t
        self.t += self.read_ns
        return value

    def sleep(self, seconds: float) -> None:
        assert seconds > 0, f"sleep({seconds})"
        ns = round(seconds * 1e9)
        assert self.last_read is not None
        self.sleep_targets.append(self.last_read + ns)
        self.t += ns

    def work(self, ns: int) -> None:
        self.t += ns


def make(policy: str = "catch_up", realtime: bool = True) -> tuple[TickClock, FakeClock]:
    fake = FakeClock()
    clock = TickClock(PERIOD, realtime, policy, SPIN, now_ns=fake.now_ns, sleep=fake.sleep)
    return clock, fake


def run_ticks(clock: TickClock, fake: FakeClock, works: list[int]) -> list[dict]:
    """The session's loop: wait, work, finish(now). One record per tick."""
    ticks = []
    for work in works:
        deadline = clock.deadline_ns
        lateness = clock.wait()
        began = fake.last_read
        fake.work(work)
        missed = clock.finish(fake.now_ns())
        ticks.append({"deadline": deadline, "lateness": lateness, "began": began, "missed": missed})
    return ticks


# --- absolute deadlines -----------------------------------------------------------------------
def test_deadlines_are_absolute_no_drift() -> None:
    clock, fake = make()
    clock.start()
    assert clock.deadline_ns == START
    # work of every length short of a period: a "sleep(dt)" loop would drift by their sum
    works = [0, 950_000, 10_000, 799_000, 500_000, 990_000, 123_457, 300_001] * 25
    ticks = run_ticks(clock, fake, works)
    n = len(works)
    assert [t["deadline"] for t in ticks] == [START + k * PERIOD for k in range(n)]
    assert clock.deadline_ns == START + n * PERIOD
    assert not any(t["missed"] for t in ticks)
    # every tick after the first starts exactly on its deadline (the first is late by the one
    # clock read between start() and wait())
    assert ticks[0]["lateness"] == READ
    assert [t["lateness"] for t in ticks[1:]] == [0] * (n - 1)
    assert [t["began"] for t in ticks[1:]] == [START + k * PERIOD for k in range(1, n)]


def test_sleep_targets_deadline_minus_spin_then_spins_to_the_deadline() -> None:
    clock, fake = make()
    clock.start()
    clock.finish(START + 300_000)  # tick 0 done early: deadline is now START + PERIOD
    fake.t = START + 300_000
    reads_before = fake.reads
    assert clock.wait() == 0
    assert fake.sleep_targets == [START + PERIOD - SPIN]
    assert fake.last_read == START + PERIOD  # the spin ended exactly on the deadline
    # the spin read the clock through the last SPIN ns (plus the read before the sleep)
    assert fake.reads - reads_before == 1 + SPIN // READ
    # counted from the read after the sleep: CPU the loop burns by design
    assert clock.spun_ns == SPIN - READ


def test_no_sleep_when_less_than_spin_remains() -> None:
    clock, fake = make()
    clock.start()
    clock.finish(START + 900_000)
    fake.t = START + PERIOD - SPIN  # exactly spin_ns left: spin only
    assert clock.wait() == 0
    assert fake.sleep_targets == []
    assert fake.last_read == START + PERIOD


def test_sleeps_happen_exactly_when_more_than_spin_remains() -> None:
    clock, fake = make()
    clock.start()
    works = [100_000, 700_000, 799_000, 900_000, 0]
    ticks = run_ticks(clock, fake, works)
    # wait() first reads the clock 2 reads after the work ended (finish's read, then its own)
    expected = [
        ticks[k + 1]["deadline"] - SPIN
        for k, work in enumerate(works[:-1])
        if PERIOD - (work + 2 * READ + (READ if k == 0 else 0)) > SPIN
    ]
    assert fake.sleep_targets == expected
    assert len(expected) == 2  # the 100 us and the 700 us tick
    assert [t["lateness"] for t in ticks[1:]] == [0] * (len(works) - 1)


def test_late_wait_returns_the_lateness_without_sleeping() -> None:
    clock, fake = make()
    clock.start()
    fake.t = START + 37_000
    assert clock.wait() == 37_000
    assert fake.sleep_targets == [] and clock.spun_ns == 0


# --- finish: what counts as a missed deadline --------------------------------------------------
@pytest.mark.parametrize("policy", OVERRUN_POLICIES)
def test_finish_at_or_before_next_deadline_is_not_missed(policy: str) -> None:
    clock, _ = make(policy)
    clock.start()
    assert clock.finish(START + PERIOD - 1) is False
    assert clock.deadline_ns == START + PERIOD
    assert clock.finish(START + 2 * PERIOD) is False  # ending exactly on it is still on time
    assert clock.deadline_ns == START + 2 * PERIOD
    assert clock.skipped == 0


def test_finish_after_next_deadline_is_missed() -> None:
    clock, _ = make("catch_up")
    clock.start()
    assert clock.finish(START + PERIOD + 1) is True
    assert clock.deadline_ns == START + PERIOD


# --- overrun policies -------------------------------------------------------------------------
def test_catch_up_keeps_the_schedule() -> None:
    clock, fake = make("catch_up")
    clock.start()
    works = [3_500_000] + [10_000] * 10  # one tick takes 3.5 periods
    ticks = run_ticks(clock, fake, works)
    assert [t["deadline"] for t in ticks] == [START + k * PERIOD for k in range(len(works))]
    # ticks 1 and 2 start late and end after their next deadline too; tick 3 catches up
    assert [t["missed"] for t in ticks] == [True, True, True] + [False] * 8
    assert ticks[1]["lateness"] == 2_503_000
    assert ticks[2]["lateness"] > ticks[3]["lateness"] > 0
    assert [t["lateness"] for t in ticks[4:]] == [0] * 7
    assert clock.skipped == 0


def test_skip_jumps_to_the_next_future_deadline() -> None:
    clock, fake = make("skip")
    clock.start()
    works = [3_500_000] + [10_000] * 5
    ticks = run_ticks(clock, fake, works)
    # tick 0 ends at START + 3.502 ms: deadlines +1, +2, +3 ms are dropped, +4 ms is next
    assert ticks[0]["missed"] is True
    assert clock.skipped == 3
    assert [t["deadline"] for t in ticks] == [START] + [START + k * PERIOD for k in range(4, 9)]
    assert not any(t["missed"] for t in ticks[1:])
    assert [t["lateness"] for t in ticks[1:]] == [0] * 5  # back on the original time base


@pytest.mark.parametrize(
    ("end", "deadline", "skipped"),
    [
        (START + PERIOD + 1, START + 2 * PERIOD, 1),
        (START + 2 * PERIOD, START + 2 * PERIOD, 1),  # ends exactly on a deadline: keep it
        (START + 2 * PERIOD + 1, START + 3 * PERIOD, 2),
        (START + 10 * PERIOD - 1, START + 10 * PERIOD, 9),
    ],
)
def test_skip_counts_the_dropped_deadlines(end: int, deadline: int, skipped: int) -> None:
    clock, _ = make("skip")
    clock.start()
    assert clock.finish(end) is True
    assert clock.deadline_ns == deadline
    assert clock.skipped == skipped
    assert clock.deadline_ns >= end  # never a deadline in the past


def test_stop_raises_overrun_stop_before_the_next_tick() -> None:
    clock, fake = make("stop")
    clock.start()
    run_ticks(clock, fake, [500_000, 999_000])  # on time: no stop
    assert clock.deadline_ns == START + 2 * PERIOD
    # the late tick has run: it is reported missed (and counted) like any other ...
    assert clock.finish(START + 3 * PERIOD + 250_000) is True
    assert clock.missed == 1
    with pytest.raises(OverrunStop) as info:  # ... and the next one does not start
        clock.wait()
    assert isinstance(info.value, SafetyStop) and isinstance(info.value, TeleopError)
    assert "250 us" in str(info.value) and "stop" in str(info.value)


@pytest.mark.parametrize("policy", ["catch_up", "skip"])
def test_max_missed_stops_at_one_more_than_allowed(policy: str) -> None:
    clock, fake = make(policy)
    clock.max_missed = 2
    clock.start()
    late = START + 10 * PERIOD
    for _ in range(3):
        clock.wait()
        late += 10 * PERIOD
        assert clock.finish(late) is True  # each tick misses its deadline
    assert clock.missed == 3
    with pytest.raises(OverrunStop, match="3 deadlines missed, more than the 2 allowed"):
        clock.wait()


def test_unknown_policy_is_refused() -> None:
    with pytest.raises(ValueError, match="overrun policy"):
        TickClock(PERIOD, True, "panic")


# --- fast mode --------------------------------------------------------------------------------
@pytest.mark.parametrize("policy", OVERRUN_POLICIES)
def test_fast_mode_never_sleeps_nor_misses(policy: str) -> None:
    def no_sleep(seconds: float) -> None:
        raise AssertionError(f"fast mode slept {seconds} s")

    fake = FakeClock()
    clock = TickClock(PERIOD, False, policy, SPIN, now_ns=fake.now_ns, sleep=no_sleep)
    clock.start()
    for _ in range(100):
        assert clock.wait() == 0
        fake.work(5 * PERIOD)  # far slower than real time: still no miss, no stop
        assert clock.finish(fake.now_ns()) is False
    assert clock.skipped == 0


# --- timing statistics ------------------------------------------------------------------------
def test_timing_stats_percentiles_on_known_data() -> None:
    stats = TimingStats(100, period_ns=150_000)
    for us in range(1, 101):
        stats.add(us * 1000, lateness_ns=2 * us * 1000, missed=us % 10 == 0)
    s = stats.summary()
    assert s["ticks"] == 100
    assert s["missed_deadlines"] == 10
    assert s["compute_us"]["p50"] == pytest.approx(50.5)
    assert s["compute_us"]["p99"] == pytest.approx(99.01)
    assert s["compute_us"]["max"] == pytest.approx(100.0)
    assert s["lateness_us"]["p50"] == pytest.approx(101.0)
    assert s["lateness_us"]["max"] == pytest.approx(200.0)
    assert s["lateness_us"]["p99.9"] == pytest.approx(2 * 99.901)
    assert s["late_over_period"] == 25  # lateness 152 ... 200 us > 150 us


def test_timing_stats_use_only_the_filled_part() -> None:
    stats = TimingStats(1000)  # preallocated for more ticks than ran: the zeros must not count
    for us in (30, 10, 20):
        stats.add(us * 1000, 0, False)
    s = stats.summary()
    assert s["ticks"] == 3 and s["missed_deadlines"] == 0
    assert s["compute_us"]["p50"] == pytest.approx(20.0)
    assert s["compute_us"]["max"] == pytest.approx(30.0)


def test_timing_stats_empty() -> None:
    s = TimingStats(10).summary()
    assert s["ticks"] == 0 and s["missed_deadlines"] == 0
    zero = {"p50": 0.0, "p99": 0.0, "p99.9": 0.0, "max": 0.0}
    assert s["compute_us"] == zero and s["lateness_us"] == zero


def test_the_wakeup_latency_request_is_held_until_the_grant_is_released(tmp_path) -> None:
    path = tmp_path / "cpu_dma_latency"  # stands in for the kernel's PM QoS file
    path.touch()
    notes: list[str] = []
    handle = hold_wakeup_latency(notes, str(path))
    assert path.read_bytes() == struct.pack("i", 0)  # 0 us, as a native int
    assert not handle.closed and notes == [f"CPU wake-up latency held at 0 us ({path})"]
    RealtimeGrant([], gc.isenabled(), wakeup_latency=handle).release()
    assert handle.closed  # the kernel drops the request with the last close


def test_a_wakeup_latency_request_not_granted_is_a_note(tmp_path) -> None:
    notes: list[str] = []
    assert hold_wakeup_latency(notes, str(tmp_path / "missing" / "cpu_dma_latency")) is None
    assert notes[0].startswith("CPU wake-up latency not held (") and "deep idle" in notes[0]


# --- the adaptive spin ------------------------------------------------------------------------
class OversleepingClock(FakeClock):
    """A fake clock whose every sleep returns ``over_ns`` late, as a loaded host's does."""

    def __init__(self, over_ns: int) -> None:
        super().__init__()
        self.over_ns = over_ns

    def sleep(self, seconds: float) -> None:
        super().sleep(seconds)
        self.t += self.over_ns


@pytest.mark.parametrize("over_us", [0, 40, 120])
def test_the_adaptive_clock_learns_how_late_its_sleeps_return(over_us: int) -> None:
    """Sleeps that return 40 us late, a spin of 5 us: the fixed clock starts every tick 35 us
    late; the adaptive one learns the overshoot (1 us a tick) and then starts each tick on
    time, spinning about the 5 us only."""
    spin, over = 5_000, over_us * 1000
    results = {}
    for adaptive in (False, True):
        fake = OversleepingClock(over)
        clock = TickClock(PERIOD, True, "catch_up", spin, now_ns=fake.now_ns, sleep=fake.sleep,
                          adaptive=adaptive)  # fmt: skip
        clock.start()
        late = []
        for _ in range(400):
            late.append(clock.wait())
            fake.work(50_000)
            clock.finish(fake.now_ns())
        spun = clock.spun_ns
        for _ in range(100):  # converged: how late, and how long it spins, per tick
            late.append(clock.wait())
            fake.work(50_000)
            clock.finish(fake.now_ns())
        results[adaptive] = (max(late[-100:]), (clock.spun_ns - spun) / 100)
    fixed_late, _ = results[False]
    late, spun = results[True]
    if over > spin:  # the fixed clock: late by the overshoot beyond its spin
        assert fixed_late >= over - spin
    assert late <= 2 * OVERSLEEP_STEP_NS + READ  # on time, within the tracker's step
    assert spun <= spin + 2 * OVERSLEEP_STEP_NS + READ
