"""The exchange stages of a tick (``teleop_rt.tick_stages``), compiled once for every build
that runs them: the in-process link's delivery (with the codec's look-ahead into each line)
and a port's stage between the codec's receive and send.

The lock-step session, the fused simulated pair, a site alone and the standalone two-port
(``teleop_rt.com.channel.TwoPort``) call these, so that the order inside a stage is written
once.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.com.codec import codec_line_ahead, codec_receive, codec_send
from teleop_rt.com.link import link_deliver
from teleop_rt.com.port import HSI, TO, Packet, Port, port_step
from teleop_rt.flat import jit


@jit
def port_stage(
    port: np.ndarray, port_i: np.ndarray, n: int, rx: np.ndarray, rx_i: np.ndarray,
    tx: np.ndarray, tx_i: np.ndarray,
) -> None:  # fmt: skip
    """The port (eq 9, 10) on the packet received, between the codec's receive and send
    (``teleop_rt.com.codec``; idle without one)."""
    port_i[Port.idx.NOW_TICK] = tx_i[Packet.idx.TICK]  # (a packet's age: the delay schedule)
    codec_receive(port, port_i, n, rx, rx_i)
    port_step(port, port_i, n, rx, rx_i, tx)
    codec_send(port, port_i, n, tx, tx_i)


@jit
def link_exchange(
    f: np.ndarray, i: np.ndarray, at: np.ndarray, n: int, port_h: np.ndarray,
    port_hi: np.ndarray, port_t: np.ndarray, port_ti: np.ndarray,
) -> None:  # fmt: skip
    """Each port's packet of this tick from the in-process link (``at``: the link's and the
    four packets' offsets, ``teleop_rt.com.link.link_offsets``), and each receiving port's
    look-ahead into the line from its peer."""
    link_deliver(f, i, at, n)
    codec_line_ahead(f, i, at, n, TO, port_h, port_hi)
    codec_line_ahead(f, i, at, n, HSI, port_t, port_ti)
