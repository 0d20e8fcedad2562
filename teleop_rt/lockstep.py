"""Two sites and an in-process link stepped in lock-step: the one-process session's tick.

The session packs both sites' blocks (``teleop_rt.site_tick.SITE_ORDER``, the HSI's then the
TO's), the link, the channel monitor, the transparency metrics and the pair's own counters into
one pair of buffers (``SESSION_ORDER``), so that one compiled call reaches everything:

    lockstep_before:  both sites sense; the link delivers; both sites up to their models; the
                      link takes this tick's packets; the monitor accounts the two-port's power
    (Python)          RNEA of each robot
    lockstep_after:   both sites' computed torque and checks; T_p, T_tau (eq 18)

Each site's arithmetic is its own kernel on its own blocks: the same kernels run a site alone,
in a process of its own.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.channel import monitor_step
from teleop_rt.com.codec import codec_line_ahead
from teleop_rt.com.link import link_deliver, link_offsets, link_push
from teleop_rt.com.port import HSI, TO
from teleop_rt.flat import Block, Int, floats_of, ints_of, jit
from teleop_rt.safety import SATURATED
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


FINDING_SITE, SATURATED_TICKS = PairState.finding_site.k, PairState.saturated_ticks.k


def link_at(offsets: np.ndarray) -> np.ndarray:
    """Where the link kernels find the link and the four packets in a session's buffers."""
    return link_offsets(offsets, LINK, HSI_SITE + TX, HSI_SITE + RX, TO_SITE + TX, TO_SITE + RX)


@jit
def lockstep_before(f: np.ndarray, i: np.ndarray, o: np.ndarray, at: np.ndarray, n: int) -> int:
    """Both sites from their fresh feedback to their models' accelerations; a finding (the
    pair's ``finding_site`` says whose) before anything is exchanged. ``at``: ``link_at``."""
    oh, ot = o[: 2 * SITE_BLOCKS], o[2 * SITE_BLOCKS : 4 * SITE_BLOCKS]
    finding = o[2 * PAIR + 1] + FINDING_SITE  # (ints by offset: a slice costs more)
    code = site_sense(f, i, oh, n)
    if code:
        i[finding] = 0
        return code
    code = site_sense(f, i, ot, n)
    if code:
        i[finding] = 1
        return code
    link_deliver(f, i, at, n)
    codec_line_ahead(f, i, at, n, TO, floats_of(f, oh, PORT), ints_of(i, oh, PORT))
    codec_line_ahead(f, i, at, n, HSI, floats_of(f, ot, PORT), ints_of(i, ot, PORT))
    site_before_models(f, i, oh, n)
    site_before_models(f, i, ot, n)
    link_push(f, i, at, n)
    monitor_step(floats_of(f, o, MONITOR), n, floats_of(f, oh, PORT), floats_of(f, ot, PORT))
    return 0


@jit
def lockstep_after(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, rnea_h: np.ndarray, rnea_t: np.ndarray
) -> int:
    """Both sites from their models' RNEA to checked motor torques; the finding (0: none)."""
    oh, ot = o[: 2 * SITE_BLOCKS], o[2 * SITE_BLOCKS : 4 * SITE_BLOCKS]
    pair = o[2 * PAIR + 1]
    code = site_after_models(f, i, oh, n, rnea_h)
    if code:
        i[pair + FINDING_SITE] = 0
        return code
    code = site_after_models(f, i, ot, n, rnea_t)
    if code:
        i[pair + FINDING_SITE] = 1
        return code
    if i[oh[2 * GUARD + 1] + SATURATED] or i[ot[2 * GUARD + 1] + SATURATED]:
        i[pair + SATURATED_TICKS] += 1
    accumulate(
        floats_of(f, o, METRICS), ints_of(i, o, METRICS), n,
        site_position(f, i, oh, n), site_position(f, i, ot, n),
        site_torque(f, i, oh, n), site_torque(f, i, ot, n),
    )  # fmt: skip
    return 0
