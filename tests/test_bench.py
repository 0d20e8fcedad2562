"""tools/bench.py: the parser of cyclictest's histogram, the host baseline the real-time figures
are compared with (cyclictest itself is not run here: it needs a minute and rt-tests)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import bench  # noqa: E402

# cyclictest -q -h 3000 output, one thread, shortened: 1 us bins (latency, count), then the
# summary lines; 10 wake-ups, one beyond the last bin
CYCLICTEST = """# /dev/cpu_dma_latency set to 0us
# Histogram
000004 000001
000005 000004
000006 000000
000020 000002
000900 000001
001500 000001
002999 000000
# Total: 000000010
# Min Latencies: 00004
# Avg Latencies: 00501
# Max Latencies: 03053
# Histogram Overflows: 00001
# Histogram Overflow at cycle number:
# Thread 0: 34603
"""


def test_cyclictest_histogram_to_percentiles_and_late_wakeups() -> None:
    got = bench.cyclictest_summary(CYCLICTEST, period_us=1000)
    # sorted: 4, 5 5 5 5, 20 20, 900, 1500, overflow (3053)
    assert got == {
        "wakeups": 10,
        "p50": 5.0,  # the 5th of 10
        "p99": 3053.0,  # the 10th: an overflow, read as the maximum
        "p99.9": 3053.0,
        "max": 3053.0,
        "late_over_period": 2,  # 1500 us and the overflow
    }
    assert bench.cyclictest_summary(CYCLICTEST, period_us=500)["late_over_period"] == 3


def test_output_without_a_histogram_is_an_error() -> None:
    with pytest.raises(ValueError, match="no histogram"):
        bench.cyclictest_summary("# Total: 000000000\n", period_us=1000)


def test_the_writers_sdk_floor_relogs_exactly_the_logs_tick_messages(tmp_path) -> None:
    """The SDK floor (bench.writer_floors) logs every message of the log's tick topics once, in
    the file's order, with the writer's MCAP options (LZ4 chunks): its figure is the writer's
    log calls, nothing more or less; the fork floor is a child that ran and was reaped."""
    from collections import Counter

    from mcap.reader import make_reader

    from teleop_rt import config
    from teleop_rt.recording.recorder import Recorder
    from teleop_rt.session import Session

    session = Session(config.load(ROOT / "configs/paper_experiment.yaml"))
    log = tmp_path / "log.mcap"
    recorder = Recorder(session, log, wait_for_room=True)
    session.run(ticks=300, recorder=recorder)
    topics = [t.name for t in recorder.layout.topics]

    def messages(path: Path) -> list[tuple[str, bytes, int]]:
        with open(path, "rb") as f:
            found = make_reader(f).iter_messages(topics=topics, log_time_order=False)
            return [(ch.topic, m.data, m.log_time) for _, ch, m in found]

    floors = bench.writer_floors(log, topics, tmp_path, repeat=1)
    relogged = messages(tmp_path / "floor-0.mcap")
    assert relogged == messages(log)
    assert Counter(t for t, _, _ in relogged) == {t: 300 for t in topics}
    with open(tmp_path / "floor-0.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert {c.compression for c in summary.chunk_indexes} == {"lz4"}
    assert floors["messages_per_tick"] == len(topics) == 4
    assert floors["sdk_log_us_per_tick"] > 0 and floors["fork_exit_ms"] >= 0
