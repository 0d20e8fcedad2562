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
