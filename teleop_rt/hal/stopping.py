"""Stop every robot together: one period of each backend's deactivation per tick, paced by the
clock, then each one's shutdown.

A CAN robot's stop takes several periods (quick stop until the drives report SWITCH ON
DISABLED, then disable voltage, then NMT pre-operational), and a drive watches its SYNC by the
wall clock: stopping the robots one after the other leaves the second robot's bus without
SYNC and RPDOs while the first is walked through its stop. ``stop_all`` steps them all, one
``deactivate_step`` each per period, until every one is done (``teleop_rt.hal.base``: the
lifecycle).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from teleop_rt.hal.base import ACTIVE, DEACTIVATING, INACTIVE, Backend

MAX_STEPS = 100_000  # the backstop: each backend's own stop is bounded far below this


def stop_all(
    backends: Sequence[Backend], period_s: float, max_steps: int = MAX_STEPS
) -> list[Backend]:
    """Begin every active backend's deactivation, then call ``deactivate_step`` on those not
    yet done once per ``period_s`` of wall time (absolute deadlines; a late step is not caught
    up with a burst) until all are done or ``max_steps`` steps were taken; then ``release``
    every backend.
    Returns the backends whose deactivation did not finish (normally none). A backend whose
    ``begin_deactivate`` / ``deactivate_step`` raises counts as done; the first exception
    (of those, or of a release) is raised once every backend is released."""
    error: BaseException | None = None
    pending: list[Backend] = []
    for b in backends:
        if b.lifecycle != ACTIVE:
            continue
        try:
            b.begin_deactivate()
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
                if not b.deactivate_step():
                    still.append(b)
            except BaseException as exc:  # noqa: BLE001
                error = error or exc
        pending = still
        steps += 1
    for b in backends:
        try:
            release(b)
        except BaseException as exc:  # noqa: BLE001
            error = error or exc
    if error is not None:
        raise error
    return pending


def release(backend: Backend) -> None:
    """After a run: an inactive backend is cleaned up (unconfigured: a simulated robot may run
    again), one whose deactivation did not finish is shut down (finalized), an unconfigured
    one (its configure failed, and released what it took) is left alone."""
    if backend.lifecycle == INACTIVE:
        backend.cleanup()
    elif backend.lifecycle in (ACTIVE, DEACTIVATING):
        backend.shutdown()
