"""The tick path allocates nothing it keeps: after warm-up, 10 000 ticks (recording on) leave
no net growth of allocated memory blocks (tracemalloc), and a leak of one object per tick
would be seen by the same measurement.

Tolerance: CPython keeps freed floats and small tuples on free lists (up to 100 floats in
3.11) that tracemalloc still counts as allocated, so a few dozen blocks come and go with no
leak; anything kept per tick would show as >= 10 000 blocks, one kept every 100 ticks as 100."""

from __future__ import annotations

import gc
import tracemalloc
from collections.abc import Callable

from teleop_rt import config
from teleop_rt.recording.recorder import Recorder
from teleop_rt.session import Session
from tests.conftest import CONFIGS

TICKS = 10_000


def net_blocks(tick: Callable[[], None], ticks: int) -> int:
    """Allocated blocks after ``ticks`` calls minus before (garbage collected on both sides)."""
    gc.collect()
    tracemalloc.start()
    try:
        before = sum(s.count for s in tracemalloc.take_snapshot().statistics("filename"))
        for _ in range(ticks):
            tick()
        gc.collect()
        after = sum(s.count for s in tracemalloc.take_snapshot().statistics("filename"))
    finally:
        tracemalloc.stop()
    return after - before


def test_ticks_with_recording_keep_no_allocation(tmp_path) -> None:
    # the paper experiment: hand operator, foam and wall, wave channel with 10 ms delay
    cfg = config.load(CONFIGS / "paper_experiment.yaml", ["channel.delay_ms=10"])
    session = Session(cfg)
    recorder = Recorder(session, tmp_path / "a.mcap")
    step, record = session.step, recorder.record

    def tick() -> None:
        step()
        record(0, 0, False)

    try:
        for _ in range(1000):  # warm-up: caches, the trajectory's first segments
            tick()
        growth = net_blocks(tick, TICKS)
    finally:
        recorder.close(None)
    assert growth < TICKS // 100, f"{growth} blocks kept over {TICKS} ticks"


def test_the_measurement_sees_a_leak_of_one_object_per_tick() -> None:
    kept: list[object] = []
    assert net_blocks(lambda: kept.append(object()), TICKS) >= TICKS
