"""Stop every robot together: one period of each backend's stop per tick, paced by the clock.

A CAN robot's stop takes several periods (quick stop until the drives report SWITCH ON
DISABLED, then disable voltage, then NMT pre-operational), and a drive watches its SYNC by the
wall clock: stopping the robots one after the other leaves the second robot's bus without
SYNC and RPDOs while the first is walked through its stop. ``stop_all`` steps them all, one
``stop_step`` each per period, until every one is done.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from teleop_rt.hal.base import Backend

MAX_STEPS = 100_000  # the backstop: each backend's own stop is bounded far below this


def stop_all(
    backends: Sequence[Backend], period_s: float, max_steps: int = MAX_STEPS
) -> list[Backend]:
    """Begin every backend's stop, then call ``stop_step`` on those not yet done once per
    ``period_s`` of wall time (absolute deadlines; a late step is not caught up with a burst)
    until all are done or ``max_steps`` steps were taken. Returns the backends whose stop did
    not finish (normally none). A backend whose ``begin_stop`` / ``stop_step`` raises counts
    as done; the first such exception is raised once the others have stopped."""
    error: BaseException | None = None
    pending: list[Backend] = []
    for b in backends:
        try:
            b.begin_stop()
            pending.append(b)
        except BaseException as exc:  # noqa: BLE001 - the other robots must still stop
            error = error or exc
    period_ns = round(period_s * 1e9)
    deadline = time.perf_counter_ns()
    steps = 0
    while pending and steps < max_steps:
        # one period after the last frame this loop (or the session's last tick) sent
        deadline += period_ns
        delay = deadline - time.perf_counter_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
        else:
            deadline = time.perf_counter_ns()
        still = []
        for b in pending:
            try:
                if not b.stop_step():
                    still.append(b)
            except BaseException as exc:  # noqa: BLE001
                error = error or exc
        pending = still
        steps += 1
    if error is not None:
        raise error
    return pending
