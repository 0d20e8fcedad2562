"""Two sites and an in-process link stepped in lock-step: the one-process session's tick.

The session packs both sites' blocks (``teleop_rt.site_tick.SITE_ORDER``, the HSI's then the
TO's), the link, the channel monitor, the transparency metrics and the pair's own counters into
one pair of buffers (``SESSION_ORDER``), so that one compiled call reaches everything. The
two kernels hold the stages of ``teleop_rt.tick_stages`` on either side of the RNEA calls, in
``tick_stages.lockstep()``'s order: ``lockstep_before`` up to the monitor, ``lockstep_after``
from computed torque to T_p, T_tau (``pair_monitor`` and ``pair_account`` are the pair's
stages, shared with a session stepped from Python).

Each site's arithmetic is its own kernel on its own blocks: the same kernels run a site alone,
in a process of its own.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.channel import monitor_step
from teleop_rt.com.exchange import link_exchange
from teleop_rt.com.link import link_offsets, link_push
from teleop_rt.flat import Block, Int, floats_of, ints_of, jit
from teleop_rt.safety import RobotGuard
from teleop_rt.site_tick import (
    GUARD,
    PORT,
    RX,
    SITE_BLOCKS,
    TX,
    site_after_models,
    site_before_models,
    site_position,
    site_sense,
    site_torque,
)
from teleop_rt.transparency_tick import accumulate

HSI_SITE, TO_SITE = 0, SITE_BLOCKS  # each site's first block
LINK, MONITOR, METRICS, PAIR = range(2 * SITE_BLOCKS, 2 * SITE_BLOCKS + 4)
SESSION_BLOCKS = 2 * SITE_BLOCKS + 4  # blocks a backend's fused tick may follow


class PairState(Block):
    """What the pair of sites counts beyond each site's own."""

    finding_site = Int("0: the HSI's, 1: the TO's finding")
    saturated_ticks = Int("ticks in which either robot's torque was saturated")


def link_at(offsets: np.ndarray) -> np.ndarray:
    """Where the link kernels find the link and the four packets in a session's buffers."""
    return link_offsets(offsets, LINK, HSI_SITE + TX, HSI_SITE + RX, TO_SITE + TX, TO_SITE + RX)


@jit
def lockstep_before(f: np.ndarray, i: np.ndarray, o: np.ndarray, at: np.ndarray, n: int) -> int:
    """Both sites from their fresh feedback to their models' accelerations; a finding (the
    pair's ``finding_site`` says whose) before anything is exchanged. ``at``: ``link_at``."""
    oh, ot = o[: 2 * SITE_BLOCKS], o[2 * SITE_BLOCKS : 4 * SITE_BLOCKS]
    finding = o[2 * PAIR + 1] + PairState.idx.FINDING_SITE  # (ints by offset: cheaper than a slice)
    code = site_sense(f, i, oh, n)
    if code:
        i[finding] = 0
        return code
    code = site_sense(f, i, ot, n)
    if code:
        i[finding] = 1
        return code
    link_exchange(
        f, i, at, n, floats_of(f, oh, PORT), ints_of(i, oh, PORT), floats_of(f, ot, PORT),
        ints_of(i, ot, PORT),
    )  # fmt: skip
    site_before_models(f, i, oh, n)
    site_before_models(f, i, ot, n)
    link_push(f, i, at, n)
    pair_monitor(f, o, n)
    return 0


@jit
def pair_monitor(f: np.ndarray, o: np.ndarray, n: int) -> None:
    """The two-port's power and energy (eq 7, 8) from both sites' ports."""
    port_h, port_t = floats_of(f, o, HSI_SITE + PORT), floats_of(f, o, TO_SITE + PORT)
    monitor_step(floats_of(f, o, MONITOR), n, port_h, port_t)


@jit
def pair_account(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int) -> None:
    """What the pair counts once both sites' torques are checked: the ticks either robot
    saturated, and T_p, T_tau (eq 18) of the sites' positions and torques."""
    oh, ot = o[: 2 * SITE_BLOCKS], o[2 * SITE_BLOCKS : 4 * SITE_BLOCKS]
    saturated = RobotGuard.idx.SATURATED
    if i[oh[2 * GUARD + 1] + saturated] or i[ot[2 * GUARD + 1] + saturated]:
        i[o[2 * PAIR + 1] + PairState.idx.SATURATED_TICKS] += 1
    accumulate(
        floats_of(f, o, METRICS), ints_of(i, o, METRICS), n,
        site_position(f, i, oh, n), site_position(f, i, ot, n),
        site_torque(f, i, oh, n), site_torque(f, i, ot, n),
    )  # fmt: skip


@jit
def lockstep_after(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, rnea_h: np.ndarray, rnea_t: np.ndarray
) -> int:
    """Both sites from their models' RNEA to checked motor torques; the finding (0: none)."""
    oh, ot = o[: 2 * SITE_BLOCKS], o[2 * SITE_BLOCKS : 4 * SITE_BLOCKS]
    finding = o[2 * PAIR + 1] + PairState.idx.FINDING_SITE
    code = site_after_models(f, i, oh, n, rnea_h)
    if code:
        i[finding] = 0
        return code
    code = site_after_models(f, i, ot, n, rnea_t)
    if code:
        i[finding] = 1
        return code
    pair_account(f, i, o, n)
    return 0
